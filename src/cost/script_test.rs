//! Script unit tests: YAML files next to a script (`name.test.yaml`) naming scenes, parameters,
//! candidate trajectories and expectations. The format is documented in
//! docs/cost-scripts.md ("Testing cost scripts"); `drivescript test-scripts` and `cargo test` run them.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};
use std::rc::Rc;

use serde::Deserialize;

use super::{CostError, CostReport, CostScript, Limits, Params, Trajectories};
use crate::io::{load_scene, rollout::Rollout, LoadOptions};
use crate::scene::Scene;

/// A test file.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TestFile {
    /// The script, relative to the test file.
    pub script: String,
    /// The cases.
    pub cases: Vec<TestCase>,
}

/// One case: a scene, parameters, a candidate and what to expect of it.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TestCase {
    /// What the case shows.
    pub name: String,
    /// The scene, relative to the test file.
    pub scene: String,
    /// Script parameters.
    #[serde(default)]
    pub params: BTreeMap<String, serde_yaml::Value>,
    /// The candidate future: `{scene: file}` (another scene's recorded future, agents matched by
    /// id), `{rollout: file.json}`, or the recorded future when absent.
    #[serde(default)]
    pub candidate: CandidateSpec,
    /// Edits applied to the candidate's future.
    #[serde(default)]
    pub edits: Vec<Edit>,
    /// Expectations.
    pub expect: Expect,
}

/// Where the candidate future comes from (at most one of the fields).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CandidateSpec {
    /// Another scene's recorded future (agents matched by id; same steps), e.g. a YAML variant
    /// of the test scene in which an agent behaves differently.
    #[serde(default)]
    pub scene: Option<String>,
    /// A rollout JSON file.
    #[serde(default)]
    pub rollout: Option<String>,
}

/// A change to one agent's candidate future, blended in linearly over `ramp` seconds from
/// `from` seconds after the current step.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Edit {
    /// The agent.
    pub agent: i64,
    /// Move sideways, metres, left of the agent's current heading.
    #[serde(default)]
    pub lateral: Option<f64>,
    /// Move by `[dx, dy]` metres.
    #[serde(default)]
    pub shift: Option<[f64; 2]>,
    /// Hold the current state for the whole future.
    #[serde(default)]
    pub freeze: bool,
    /// Add a sideways sinusoid `[amplitude, period]` (metres left of the current heading,
    /// seconds): `amplitude · sin(2π t / period)` at `t` seconds after the current step.
    #[serde(default)]
    pub sway: Option<[f64; 2]>,
    /// Start of the change, seconds after the current step.
    #[serde(default)]
    pub from: f64,
    /// Seconds over which the change grows to its full size.
    #[serde(default)]
    pub ramp: f64,
}

/// The least distance, metres, an edit must move its agent at some future step: below it
/// the case runs on what is, to any script, the unedited future.
const MIN_EDIT_MOVE: f64 = 1e-6;

/// The shortest `sway` period, seconds: far below any time step, far above where the phase
/// `t / period` stops being a number.
const MIN_SWAY_PERIOD: f64 = 1e-3;

impl Edit {
    /// Refuses values that would make the candidate's positions NaN or infinite (a `sway`
    /// period of 0 divides by zero): the cost engine cannot say which edit made them so.
    fn check(&self) -> Result<(), String> {
        let finite = |field: &str, v: f64| {
            if v.is_finite() {
                Ok(())
            } else {
                Err(format!("`{field}` is {v}, not a finite number"))
            }
        };
        if let Some(d) = self.lateral {
            finite("lateral", d)?;
        }
        if let Some([dx, dy]) = self.shift {
            finite("shift", dx)?;
            finite("shift", dy)?;
        }
        if let Some([amp, period]) = self.sway {
            finite("sway amplitude", amp)?;
            finite("sway period", period)?;
            // A period of 1e-310 s is above 0, but `t / period` overflows: the sine of
            // infinity made NaN positions, on which the script's Frenet projection panicked.
            if period < MIN_SWAY_PERIOD {
                return Err(format!(
                    "`sway: [{}, {}]`: the period (seconds, the second number) must be at \
                     least {MIN_SWAY_PERIOD}",
                    crate::geom::num(amp),
                    crate::geom::num(period)
                ));
            }
        }
        // Finite but far beyond any map (`lateral: 1e300`) made the candidate's positions
        // infinite, reported as the script's "term ... is inf".
        let near = |field: &str, v: f64| {
            if v.abs() > crate::geom::MAX_COORD {
                Err(format!(
                    "`{field}` is {}: farther than {:e} m, beyond any map",
                    crate::geom::num(v),
                    crate::geom::MAX_COORD
                ))
            } else {
                Ok(())
            }
        };
        if let Some(d) = self.lateral {
            near("lateral", d)?;
        }
        if let Some([dx, dy]) = self.shift {
            near("shift", dx)?;
            near("shift", dy)?;
        }
        if let Some([amp, _]) = self.sway {
            near("sway amplitude", amp)?;
        }
        if self.lateral.is_none() && self.shift.is_none() && self.sway.is_none() && !self.freeze {
            return Err("it changes nothing: give lateral, shift, sway or freeze".into());
        }
        // Given, but of size 0 (`shift: [0, 0]`, `sway: [0, 2]`): the case ran on the
        // unedited future, as one of no edit does.
        let zero = self.lateral.is_none_or(|d| d == 0.0)
            && self.shift.is_none_or(|[x, y]| x == 0.0 && y == 0.0)
            && self.sway.is_none_or(|[amp, _]| amp == 0.0);
        if zero && !self.freeze {
            return Err(
                "it changes nothing: its lateral, shift and sway are 0; give one of some size, \
                 or freeze"
                    .into(),
            );
        }
        // `freeze` holds the current state over the whole future, so anything beside it was
        // dropped without a word and the case ran on a future the file did not describe.
        if self.freeze {
            let ignored: Vec<&str> = [
                ("lateral", self.lateral.is_some()),
                ("shift", self.shift.is_some()),
                ("sway", self.sway.is_some()),
                ("from", self.from != 0.0),
                ("ramp", self.ramp != 0.0),
            ]
            .into_iter()
            .filter_map(|(f, given)| given.then_some(f))
            .collect();
            if !ignored.is_empty() {
                return Err(format!(
                    "`freeze` holds the current state for the whole future, so `{}` would be \
                     ignored: give freeze alone, or a separate edit",
                    ignored.join("`, `")
                ));
            }
        }
        finite("from", self.from)?;
        finite("ramp", self.ramp)?;
        // Seconds after the current step: a negative one behaved as 0, the past untouched, so
        // the case ran on another edit than the file wrote.
        if self.from < 0.0 {
            return Err(format!(
                "`from` is {}: seconds after the current step, at least 0 (an edit changes \
                 the future only)",
                crate::geom::num(self.from)
            ));
        }
        if self.ramp < 0.0 {
            return Err(format!(
                "`ramp` is {}: seconds, at least 0",
                crate::geom::num(self.ramp)
            ));
        }
        Ok(())
    }
}

/// What a case expects.
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Expect {
    /// The weighted total is at most this.
    #[serde(default)]
    pub total_below: Option<f64>,
    /// The weighted total is above this.
    #[serde(default)]
    pub total_above: Option<f64>,
    /// These terms (unweighted) are at most these values.
    #[serde(default)]
    pub terms_below: BTreeMap<String, f64>,
    /// These terms are above these values.
    #[serde(default)]
    pub terms_above: BTreeMap<String, f64>,
    /// This term has the largest weighted value.
    #[serde(default)]
    pub largest_term: Option<String>,
    /// A small step against the gradient lowers the total.
    #[serde(default)]
    pub descends: bool,
    /// Against the gradient, this agent moves (summed over its future) along this direction.
    #[serde(default)]
    pub towards: Option<Towards>,
    /// These agents get no gradient at all: the terms leave them where they are (an agent
    /// held with `hold`, say, that no other term is about).
    #[serde(default)]
    pub still: Vec<i64>,
    /// Exactly these exemptions from realism are asked for (`allow(...)`), by agent id.
    #[serde(default)]
    pub allows: Option<Allows>,
    /// Compiling, validating or evaluating fails with a message containing this.
    #[serde(default)]
    pub error: Option<String>,
}

/// The exemptions from realism a script asks for, by agent id (order does not matter).
#[derive(Debug, Clone, Default, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Allows {
    /// Agents allowed to back up (`allow(a, "reverse")`).
    #[serde(default)]
    pub reverse: Vec<i64>,
    /// Pairs allowed to touch (`allow(a, "collide", b)`).
    #[serde(default)]
    pub collide: Vec<[i64; 2]>,
}

impl Expect {
    /// Refuses an expectation that cannot fail or cannot pass whatever the script does: a
    /// threshold that is not a finite number (`total_below: .inf` passes always, `.nan`
    /// never), a `towards` direction of zero length (its descent is NaN), an empty `error`
    /// (every message contains it).
    fn check(&self) -> Result<(), String> {
        let finite = |field: String, v: f64| {
            if v.is_finite() {
                Ok(())
            } else {
                Err(format!("`{field}` is {v}: a threshold is a finite number"))
            }
        };
        if let Some(v) = self.total_below {
            finite("total_below".into(), v)?;
        }
        if let Some(v) = self.total_above {
            finite("total_above".into(), v)?;
        }
        for (k, v) in &self.terms_below {
            finite(format!("terms_below.{}", crate::io::name::shown(k)), *v)?;
        }
        for (k, v) in &self.terms_above {
            finite(format!("terms_above.{}", crate::io::name::shown(k)), *v)?;
        }
        // A total (or a term) at most `below` and above `above`, where `below <= above`:
        // the case failed whatever the script did.
        let both = |what: String, below: f64, above: f64| {
            if below <= above {
                Err(format!(
                    "{what} must be at most {} and above {}: no value is both; the thresholds \
                     are swapped or mistyped",
                    crate::geom::num(below),
                    crate::geom::num(above)
                ))
            } else {
                Ok(())
            }
        };
        if let (Some(b), Some(a)) = (self.total_below, self.total_above) {
            both("the total".into(), b, a)?;
        }
        for (k, b) in &self.terms_below {
            if let Some(a) = self.terms_above.get(k) {
                both(format!("term {}", crate::io::name::shown(k)), *b, *a)?;
            }
        }
        if let Some(t) = &self.towards {
            let [dx, dy] = t.direction;
            if !(dx.is_finite() && dy.is_finite()) || dx == 0.0 && dy == 0.0 {
                return Err(format!(
                    "`towards.direction` is [{}, {}]: a direction is two finite numbers, not both 0",
                    crate::geom::num(dx),
                    crate::geom::num(dy)
                ));
            }
            // The run normalises the direction through its squared length: [1e308, 1e308]
            // overflowed to a zero direction and [1e-200, 0] underflowed to NaN, and either
            // case failed whatever the script did.
            if !(dx * dx + dy * dy).is_normal() {
                return Err(format!(
                    "`towards.direction` is [{}, {}]: its length is out of range; give a \
                     direction of ordinary size, such as [1, 0]",
                    crate::geom::num(dx),
                    crate::geom::num(dy)
                ));
            }
        }
        if let Some(a) = &self.allows {
            // An agent is never checked against itself, so the pair was never among the
            // script's exemptions and the case failed whatever the script did.
            if let Some([i, _]) = a.collide.iter().find(|[i, j]| i == j) {
                return Err(format!(
                    "`allows.collide` pairs agent {i} with itself: a pair is two different agents"
                ));
            }
        }
        // A case that expects an error stops at it: a threshold beside it was never looked
        // at, and `{error: ..., total_below: -5}` passed.
        if self.error.is_some() {
            let unchecked = Expect {
                error: None,
                ..self.clone()
            };
            if !unchecked.checks_nothing() {
                return Err(
                    "`error` expects the script to fail, so nothing else given beside it can be \
                     checked: put the other expectations in a case of their own"
                        .into(),
                );
            }
        }
        if self.error.as_deref().is_some_and(|e| e.trim().is_empty()) {
            return Err(
                "`error` is empty: every message contains it; give a part of the message expected"
                    .into(),
            );
        }
        Ok(())
    }

    /// Whether the case would pass whatever the script does (`expect: {}`).
    pub fn checks_nothing(&self) -> bool {
        self.total_below.is_none()
            && self.total_above.is_none()
            && self.terms_below.is_empty()
            && self.terms_above.is_empty()
            && self.largest_term.is_none()
            && !self.descends
            && self.towards.is_none()
            && self.still.is_empty()
            && self.allows.is_none()
            && self.error.is_none()
    }
}

/// A direction the descent should move an agent.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Towards {
    /// The agent.
    pub agent: i64,
    /// World-frame direction `[dx, dy]`.
    pub direction: [f64; 2],
    /// Only this future step (negative counts from the end) instead of the sum over all.
    #[serde(default)]
    pub step: Option<i64>,
}

/// The outcome of one case.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct CaseResult {
    /// The test file.
    pub file: String,
    /// The case's name.
    pub case: String,
    /// Whether every expectation held.
    pub passed: bool,
    /// The measured quantities (and what failed).
    pub detail: String,
}

/// Errors that keep a test file from running at all.
#[derive(Debug, thiserror::Error)]
pub enum ScriptTestError {
    /// The file could not be read.
    #[error("{path}: {message}")]
    Read {
        /// The file.
        path: String,
        /// Why.
        message: String,
    },
    /// A file it names cannot be read (the message names the file).
    #[error("{0}")]
    Io(String),
}

/// The most a test file may hold: the largest in scripts/ is under 2 KB.
pub const MAX_TEST_FILE_BYTES: u64 = 1 << 20;

/// Test files (`*.test.yaml`) under the given files or directories, sorted.
pub fn find_test_files(roots: &[PathBuf]) -> Result<Vec<PathBuf>, ScriptTestError> {
    let mut seen = std::collections::HashSet::new();
    let mut out = Vec::new();
    find_in(roots, &mut seen, &mut out)?;
    Ok(out)
}

/// [`find_test_files`] walking each directory once: a link back to a directory above (`ln -s
/// . loop`) ran and counted every test of it 41 times, once per link the OS follows before it
/// gives up.
fn find_in(
    roots: &[PathBuf],
    seen: &mut std::collections::HashSet<(u64, u64)>,
    out: &mut Vec<PathBuf>,
) -> Result<(), ScriptTestError> {
    for r in roots {
        if r.is_dir() {
            let id = crate::io::file_id(r).map_err(|e| ScriptTestError::Read {
                path: r.display().to_string(),
                message: e.to_string(),
            })?;
            if !seen.insert(id) {
                continue;
            }
            let mut entries: Vec<PathBuf> = std::fs::read_dir(r)
                .map_err(|e| ScriptTestError::Read {
                    path: r.display().to_string(),
                    message: e.to_string(),
                })?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .collect();
            entries.sort();
            for p in entries {
                if p.is_dir() {
                    find_in(&[p], seen, out)?;
                } else if p.to_string_lossy().ends_with(".test.yaml") {
                    out.push(p);
                }
            }
        } else if r.extension().is_some_and(|e| e == "rhai") {
            // Read as a test file, a script was "line 1, column 1: unknown field `// Follow`,
            // expected `script` or `cases`": the user meant its tests.
            let tests = r.with_extension("test.yaml");
            return Err(ScriptTestError::Read {
                path: r.display().to_string(),
                message: format!(
                    "is a cost script, not a test file: test-scripts runs *.test.yaml files \
                     ({} holds this script's tests when it has any)",
                    crate::io::name::terminal_safe(&tests.display().to_string())
                ),
            });
        } else if r.exists() {
            out.push(r.clone());
        } else {
            return Err(ScriptTestError::Read {
                path: r.display().to_string(),
                message: "no such file or directory".into(),
            });
        }
    }
    Ok(())
}

fn param_args(params: &BTreeMap<String, serde_yaml::Value>) -> Vec<String> {
    params
        .iter()
        .map(|(k, v)| {
            let v = match v {
                serde_yaml::Value::String(s) => s.clone(),
                other => serde_yaml::to_string(other)
                    .unwrap_or_default()
                    .trim()
                    .to_string(),
            };
            format!("{k}={v}")
        })
        .collect()
}

/// Refuses an edit of `scene`'s candidate that names no agent of it, or that starts after its
/// last future step: it changed nothing, and the case ran on the unedited future.
fn check_edit(scene: &Scene, e: &Edit) -> Result<(), String> {
    if !scene.agents.iter().any(|x| x.id == e.agent) {
        return Err(format!("edit: no agent {}", e.agent));
    }
    let last = super::VarLayout::of(scene).steps as f64 * scene.meta.dt;
    if !e.freeze && e.from > last {
        return Err(format!(
            "edit of agent {} starts {} s after the current step, after the last future step \
             ({} s): it changes nothing",
            e.agent,
            crate::geom::num(e.from),
            crate::geom::num(last)
        ));
    }
    Ok(())
}

fn apply_edit(scene: &Scene, traj: &mut Trajectories, e: &Edit) -> Result<(), String> {
    let a = scene
        .agents
        .iter()
        .position(|x| x.id == e.agent)
        .ok_or_else(|| format!("edit: no agent {}", e.agent))?;
    let cur = scene.agents[a].states[scene.meta.current_step];
    let n = traj.layout.steps;
    let dt = scene.meta.dt;
    // The farthest the edit moves the agent: a ramp of 1e300 s, or a sway of period 1e300 s,
    // is of some size but moves nothing within the future, and the case ran on the unedited
    // future, as one of no edit does.
    let mut moved = 0.0f64;
    for k in 0..n {
        let i = a * n + k;
        if e.freeze {
            traj.xyh[i] = [cur.x, cur.y, cur.heading];
            traj.valid[i] = cur.valid;
            continue;
        }
        let t = (k + 1) as f64 * dt;
        let w = if t < e.from {
            0.0
        } else if e.ramp > 0.0 {
            ((t - e.from) / e.ramp).min(1.0)
        } else {
            1.0
        };
        let before = traj.xyh[i];
        if let Some(d) = e.lateral {
            let (s, c) = cur.heading.sin_cos();
            traj.xyh[i][0] += -s * d * w;
            traj.xyh[i][1] += c * d * w;
        }
        if let Some([amp, period]) = e.sway {
            // Blended in from `from` over `ramp` like every other edit: the sway started at
            // the current step whatever `from` said.
            let d = amp * (std::f64::consts::TAU * t / period).sin() * w;
            let (s, c) = cur.heading.sin_cos();
            traj.xyh[i][0] += -s * d;
            traj.xyh[i][1] += c * d;
        }
        if let Some([dx, dy]) = e.shift {
            traj.xyh[i][0] += dx * w;
            traj.xyh[i][1] += dy * w;
        }
        moved = moved.max((traj.xyh[i][0] - before[0]).hypot(traj.xyh[i][1] - before[1]));
    }
    if !e.freeze && moved < MIN_EDIT_MOVE {
        return Err(format!(
            "edit of agent {} moves it at most {} m over the future (ramp {} s{}): it changes \
             nothing; give a shorter ramp or period, or a larger size",
            e.agent,
            crate::geom::num(moved),
            crate::geom::num(e.ramp),
            e.sway
                .map(|[_, p]| format!(", sway period {} s", crate::geom::num(p)))
                .unwrap_or_default()
        ));
    }
    Ok(())
}

struct Runner {
    scenes: HashMap<PathBuf, Rc<Scene>>,
}

impl Runner {
    fn scene(&mut self, p: &Path) -> Result<Rc<Scene>, String> {
        if let Some(s) = self.scenes.get(p) {
            return Ok(s.clone());
        }
        let s = Rc::new(load_scene(p, 0, &LoadOptions::default()).map_err(|e| e.to_string())?);
        self.scenes.insert(p.to_path_buf(), s.clone());
        Ok(s)
    }

    fn run_case(
        &mut self,
        dir: &Path,
        script_path: &Path,
        source: &str,
        c: &TestCase,
    ) -> Result<(bool, String), String> {
        let scene = self.scene(&dir.join(&c.scene))?;
        for e in &c.edits {
            check_edit(&scene, e)?;
        }
        let params = Params::parse(&param_args(&c.params)).map_err(|e| e.to_string())?;
        // A parameter the script never reads (`gapp: 30` for `gap`) ran the case on the
        // default, and it passed; `cost --param` and `simulate --param` refuse it.
        crate::cost::check_params(&[source], &params).map_err(|e| format!("params: {e}"))?;
        let name = script_path.display().to_string();
        // The candidate is the test file's, read before the script runs: a candidate that
        // could not be read was reported as the script's "trajectories do not fit the scene".
        let candidate = match (&c.candidate.scene, &c.candidate.rollout) {
            (None, None) => Trajectories::recorded(&scene),
            (Some(_), Some(_)) => return Err("candidate: give scene or rollout, not both".into()),
            (Some(p), None) => {
                let other = self
                    .scene(&dir.join(p))
                    .map_err(|m| format!("candidate.scene: {m}"))?;
                // Another recording of the same agents stands for a future of this scene:
                // everything else about it must match.
                let mut r = Rollout::from_scene(&other);
                r.scene_id = scene.meta.scenario_id.clone();
                Trajectories::from_rollout(&scene, &r)
                    .map_err(|m| format!("candidate.scene: {p}: {m}"))?
            }
            (None, Some(p)) => {
                let r =
                    Rollout::read(&dir.join(p)).map_err(|e| format!("candidate.rollout: {e}"))?;
                Trajectories::from_rollout(&scene, &r)
                    .map_err(|m| format!("candidate.rollout: {p}: {m}"))?
            }
        };
        let outcome: Result<(CostScript, CostReport, Trajectories), CostError> = (|| {
            let script =
                CostScript::compile(source, &name, scene.clone(), &params, &Limits::default())?;
            script.validate()?;
            let mut traj = candidate;
            for e in &c.edits {
                apply_edit(&scene, &mut traj, e).map_err(|m| CostError::Shape {
                    script: name.clone(),
                    message: m,
                })?;
            }
            let report = script.evaluate(&traj)?;
            Ok((script, report, traj))
        })();
        let x = &c.expect;
        let (script, report, traj) = match (outcome, &x.error) {
            (Err(e), Some(want)) => {
                let msg = e.to_string();
                // Matched in what the error says, after the script's name that begins it:
                // `error: "accident"` passed for any error of accident.rhai.
                let shown = crate::io::name::one_line(&name);
                let said = msg.strip_prefix(shown.as_str()).unwrap_or(&msg);
                return Ok((said.contains(want.as_str()), format!("error: {msg}")));
            }
            (Err(e), None) => return Ok((false, format!("unexpected error: {e}"))),
            (Ok((_, r, _)), Some(want)) => {
                return Ok((
                    false,
                    format!(
                        "expected an error containing {want:?}, got total {:.4}",
                        r.total
                    ),
                ))
            }
            (Ok(v), None) => v,
        };
        let mut detail: Vec<String> = report
            .terms
            .iter()
            .map(|t| format!("{}={:.4}", t.name, t.value))
            .collect();
        detail.insert(0, format!("total={:.4}", report.total));
        let mut failed: Vec<String> = Vec::new();
        let mut fail = |cond: bool, what: String| {
            if !cond {
                failed.push(format!("FAILED {what}"));
            }
        };
        if let Some(v) = x.total_below {
            fail(report.total <= v, format!("total <= {v}"));
        }
        if let Some(v) = x.total_above {
            fail(report.total > v, format!("total > {v}"));
        }
        for (name, v) in &x.terms_below {
            match report.term(name) {
                Some(t) => fail(t.value <= *v, format!("{name} <= {v}")),
                None => fail(false, format!("no term {name}")),
            }
        }
        for (name, v) in &x.terms_above {
            match report.term(name) {
                Some(t) => fail(t.value > *v, format!("{name} > {v}")),
                None => fail(false, format!("no term {name}")),
            }
        }
        if let Some(name) = &x.largest_term {
            let top = report
                .terms
                .iter()
                .max_by(|a, b| (a.weight * a.value).total_cmp(&(b.weight * b.value)))
                .map(|t| t.name.clone());
            fail(
                top.as_deref() == Some(name.as_str()),
                // Said plainly: `(it is Some("x"))` was Rust's debug form (issue 32).
                format!(
                    "largest term is {name} (it is {})",
                    top.as_deref()
                        .unwrap_or("none: the script declared no term")
                ),
            );
        }
        let gnorm = report.gradient.iter().map(|g| g * g).sum::<f64>().sqrt();
        if x.descends {
            let mut step = traj.clone();
            let eps = 1e-3 / gnorm.max(1e-12);
            step.apply(&report.gradient, -eps);
            let after = script.evaluate(&step).map_err(|e| e.to_string())?.total;
            detail.push(format!(
                "after a {:.0e} m descent step total={after:.6}",
                1e-3
            ));
            fail(
                gnorm > 0.0 && after < report.total,
                "a step against the gradient lowers the total".into(),
            );
        }
        if let Some(tw) = &x.towards {
            let a = scene
                .agents
                .iter()
                .position(|z| z.id == tw.agent)
                .ok_or(format!("towards: no agent {}", tw.agent))?;
            let n = traj.layout.steps;
            let (mut gx, mut gy) = (0.0, 0.0);
            let steps: Vec<usize> = match tw.step {
                None => (0..n).collect(),
                Some(k) => {
                    let j = if k < 0 { n as i64 + k } else { k };
                    if j < 0 || j >= n as i64 {
                        return Err(format!("towards: step {k} is outside the {n} future steps"));
                    }
                    vec![j as usize]
                }
            };
            for k in steps {
                gx -= report.gradient[(a * n + k) * 3];
                gy -= report.gradient[(a * n + k) * 3 + 1];
            }
            let d = nalgebra::Vector2::new(tw.direction[0], tw.direction[1]).normalize();
            let along = gx * d.x + gy * d.y;
            detail.push(format!(
                "descent of agent {} along {:?}: {along:.4}",
                tw.agent, tw.direction
            ));
            fail(
                along > 0.0,
                format!(
                    "descent moves agent {} towards {:?}",
                    tw.agent, tw.direction
                ),
            );
        }
        for id in &x.still {
            let a = scene
                .agents
                .iter()
                .position(|z| z.id == *id)
                .ok_or(format!("still: no agent {id}"))?;
            let n = traj.layout.steps;
            let moved = report.gradient[a * n * 3..(a + 1) * n * 3]
                .iter()
                .map(|g| g * g)
                .sum::<f64>()
                .sqrt();
            detail.push(format!("gradient on agent {id}: {moved:.3e}"));
            fail(moved == 0.0, format!("agent {id} gets no gradient"));
        }
        if let Some(want) = &x.allows {
            let named = want.reverse.iter().chain(want.collide.iter().flatten());
            if let Some(absent) = named
                .clone()
                .find(|&&i| !scene.agents.iter().any(|z| z.id == i))
            {
                return Err(format!("allows: no agent {absent}"));
            }
            let id = |i: usize| scene.agents[i].id;
            let mut got_rev: Vec<i64> = report.may_reverse.iter().map(|&i| id(i)).collect();
            let mut got_col: Vec<[i64; 2]> = report
                .may_collide
                .iter()
                .map(|&(i, j)| [id(i).min(id(j)), id(i).max(id(j))])
                .collect();
            let mut want_rev = want.reverse.clone();
            let mut want_col: Vec<[i64; 2]> = want
                .collide
                .iter()
                .map(|p| [p[0].min(p[1]), p[0].max(p[1])])
                .collect();
            for v in [&mut got_rev, &mut want_rev] {
                v.sort_unstable();
                v.dedup();
            }
            for v in [&mut got_col, &mut want_col] {
                v.sort_unstable();
                v.dedup();
            }
            detail.push(format!("allows reverse {got_rev:?}, collide {got_col:?}"));
            fail(
                got_rev == want_rev && got_col == want_col,
                format!("allows exactly reverse {want_rev:?} and collide {want_col:?}"),
            );
        }
        let ok = failed.is_empty();
        detail.extend(failed);
        Ok((ok, detail.join(", ")))
    }
}

/// Runs every case of a test file.
pub fn run_test_file(path: &Path) -> Result<Vec<CaseResult>, ScriptTestError> {
    // The I/O error names the file itself.
    let text = crate::io::read_regular_text(path, MAX_TEST_FILE_BYTES, "a script test file")
        .map_err(|e| ScriptTestError::Io(e.to_string()))?;
    crate::io::yaml::check_text(&text).map_err(|message| ScriptTestError::Read {
        path: path.display().to_string(),
        message,
    })?;
    let file: TestFile = serde_yaml::from_str(&text).map_err(|e| ScriptTestError::Read {
        path: path.display().to_string(),
        message: match e.location() {
            Some(l) => format!(
                "line {}, column {}: {}",
                l.line(),
                l.column(),
                crate::io::without_position(&e.to_string(), l.line(), l.column())
            ),
            None => e.to_string(),
        },
    })?;
    let invalid = |message: String| ScriptTestError::Read {
        path: path.display().to_string(),
        message,
    };
    if file.cases.is_empty() {
        return Err(invalid("no cases: a test file needs at least one".into()));
    }
    // Case names are printed in the results table and reports: a newline in one faked a line
    // of the table, an escape sequence reached the terminal.
    for (k, c) in file.cases.iter().enumerate() {
        if let Err(bad) = crate::io::name::check_name(&c.name) {
            return Err(invalid(format!(
                "cases[{k}]: name \"{}\" contains {bad}",
                crate::io::name::shown(&c.name)
            )));
        }
        // A row of no name (`name: ''`, or spaces) said nothing of which case it was, and a
        // name shown as blank could not be told from the table's empty cells.
        if c.name.trim().is_empty() {
            return Err(invalid(format!(
                "cases[{k}]: the name {:?} is blank: give each case a name it can be told by",
                c.name
            )));
        }
        // Two rows of one name in the results table could not be told apart: which failed?
        if let Some(j) = file.cases[..k].iter().position(|o| o.name == c.name) {
            return Err(invalid(format!(
                "cases[{k}]: the name {:?} is also cases[{j}]'s: give each case its own name",
                c.name
            )));
        }
    }
    if let Some(c) = file.cases.iter().find(|c| c.expect.checks_nothing()) {
        return Err(invalid(format!(
            "case {:?}: `expect` checks nothing (give at least one of total_below, total_above, terms_below, terms_above, largest_term, descends, towards, still, error)",
            c.name
        )));
    }
    for c in &file.cases {
        c.expect
            .check()
            .map_err(|m| invalid(format!("case {:?}: expect: {m}", c.name)))?;
        // A list or a map was written out as YAML and read as a word ("agent(a: 1): an agent
        // id is a whole number, not a word"), or refused for the line break inside it.
        for (k, v) in &c.params {
            use serde_yaml::Value as V;
            let kind = match v {
                V::Null => Some("nothing (null)"),
                V::Sequence(_) => Some("a list"),
                V::Mapping(_) => Some("a map"),
                V::Tagged(_) => Some("a tagged value"),
                V::Bool(_) | V::Number(_) | V::String(_) => None,
            };
            if let Some(kind) = kind {
                return Err(invalid(format!(
                    "case {:?}: params.{}: is {kind}; a parameter is a number, a word or \
                     true/false",
                    c.name,
                    crate::io::name::shown(k)
                )));
            }
        }
        if c.candidate.scene.is_some() && c.candidate.rollout.is_some() {
            return Err(invalid(format!(
                "case {:?}: candidate: give `scene` or `rollout`, not both",
                c.name
            )));
        }
        for (k, e) in c.edits.iter().enumerate() {
            e.check().map_err(|m| {
                invalid(format!(
                    "case {:?}: edit {} (agent {}): {m}",
                    c.name,
                    k + 1,
                    e.agent
                ))
            })?;
            // Edits apply in order, and `freeze` sets the agent's whole future to its current
            // state: an earlier edit of the same agent (`[{agent: 3, shift: [5, 0]}, {agent:
            // 3, freeze: true}]`) was undone without a word.
            if let Some(j) = c.edits[..k]
                .iter()
                .position(|o| e.freeze && o.agent == e.agent)
            {
                return Err(invalid(format!(
                    "case {:?}: edit {} (agent {}): `freeze` holds the current state for the \
                     whole future, so edit {} of the same agent would be undone: give freeze \
                     alone, or first",
                    c.name,
                    k + 1,
                    e.agent,
                    j + 1
                )));
            }
        }
    }
    let dir = path.parent().unwrap_or(Path::new("."));
    let script_path = dir.join(&file.script);
    let source =
        super::read_script(&script_path).map_err(|e| ScriptTestError::Io(e.to_string()))?;
    let mut runner = Runner {
        scenes: HashMap::new(),
    };
    Ok(file
        .cases
        .iter()
        .map(|c| {
            let (passed, detail) = runner
                .run_case(dir, &script_path, &source, c)
                .unwrap_or_else(|m| (false, format!("case could not run: {m}")));
            CaseResult {
                file: path.display().to_string(),
                case: c.name.clone(),
                passed,
                detail,
            }
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Runs one case of `script` (under scripts/) on the highway scene with `expect`.
    fn case(script: &str, params: &str, expect: &str) -> CaseResult {
        let dir = tempfile::tempdir().unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts");
        let t = dir.path().join("x.test.yaml");
        std::fs::write(
            &t,
            format!(
                "script: {}\ncases:\n  - name: c\n    scene: {}\n    params: {params}\n    expect: {expect}\n",
                root.join(script).display(),
                root.join("scenes/highway.yaml").display()
            ),
        )
        .unwrap();
        let mut r = run_test_file(&t).unwrap();
        assert_eq!(r.len(), 1);
        r.remove(0)
    }

    #[test]
    fn an_edit_of_zero_period_is_refused_naming_the_case_and_field() {
        let dir = tempfile::tempdir().unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts");
        for (edit, want) in [
            ("{agent: 2, sway: [1.0, 0.0]}", "sway: [1, 0]"),
            ("{agent: 2, sway: [1.0, -2.0]}", "must be at least 0.001"),
            // Above 0, but the phase overflowed to NaN positions and the script's Frenet
            // projection panicked.
            ("{agent: 2, sway: [1.0, 1e-310]}", "must be at least 0.001"),
            ("{agent: 2, sway: [.nan, 2.0]}", "`sway amplitude` is NaN"),
            ("{agent: 2, lateral: .inf}", "`lateral` is inf"),
            ("{agent: 2, shift: [0, .nan]}", "`shift` is NaN"),
            ("{agent: 2, lateral: 1, ramp: -1}", "`ramp` is -1"),
            // Behaved as `from: 0`.
            (
                "{agent: 2, lateral: 1, from: -2}",
                "`from` is -2: seconds after the current step, at least 0",
            ),
            // Made the positions infinite, blamed on the script ("term ... is inf").
            (
                "{agent: 2, lateral: 1e300}",
                "`lateral` is 1e300: farther than 1e7 m",
            ),
            ("{agent: 2, shift: [0, -2e7]}", "`shift` is -2e7: farther"),
            (
                "{agent: 2, from: 1}",
                "changes nothing: give lateral, shift, sway or freeze",
            ),
            // The shift (or the start) was dropped without a word and the case passed on
            // the frozen future.
            (
                "{agent: 2, freeze: true, shift: [-45, 0]}",
                "`freeze` holds the current state for the whole future, so `shift` would be ignored",
            ),
            (
                "{agent: 2, freeze: true, lateral: 1, from: 2}",
                "so `lateral`, `from` would be ignored",
            ),
        ] {
            let t = dir.path().join("x.test.yaml");
            std::fs::write(
                &t,
                format!(
                    "script: {}\ncases:\n  - name: swaying\n    scene: {}\n    params: {{attacker: 4, target: 2}}\n    edits: [{edit}]\n    expect: {{total_below: 1}}\n",
                    root.join("accident.rhai").display(),
                    root.join("scenes/highway.yaml").display()
                ),
            )
            .unwrap();
            let e = run_test_file(&t).unwrap_err().to_string();
            assert!(
                e.contains("x.test.yaml")
                    && e.contains("case \"swaying\": edit 1 (agent 2)")
                    && e.contains(want),
                "{edit}: {e}"
            );
        }
    }

    #[test]
    fn an_edit_that_moves_nothing_within_the_future_is_refused() {
        // A ramp or a sway period far beyond the future moved the agent by 1e-299 m: the case
        // passed on the unedited future.
        let dir = tempfile::tempdir().unwrap();
        for (edit, want) in [
            ("{agent: 2, lateral: 1.0, ramp: 1e300}", "(ramp 1e300 s)"),
            ("{agent: 2, sway: [1.0, 1e300]}", "sway period 1e300 s"),
        ] {
            let r = accident_case(
                dir.path(),
                &format!("    edits: [{edit}]\n    expect: {{total_above: 0}}\n"),
            )
            .unwrap();
            assert!(
                !r[0].passed
                    && r[0].detail.contains("edit of agent 2 moves it at most")
                    && r[0].detail.contains(want),
                "{edit}: {}",
                r[0].detail
            );
        }
        // A long ramp that still moves the agent is an edit.
        let r = accident_case(
            dir.path(),
            "    edits: [{agent: 2, lateral: 1.0, ramp: 100}]\n    expect: {total_above: 0}\n",
        )
        .unwrap();
        assert!(!r[0].detail.contains("moves it at most"), "{}", r[0].detail);
    }

    /// `run_test_file` on one case of accident.rhai on the highway with `rest` (edits and
    /// expect lines).
    fn accident_case(dir: &Path, rest: &str) -> Result<Vec<CaseResult>, ScriptTestError> {
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts");
        let t = dir.join("x.test.yaml");
        std::fs::write(
            &t,
            format!(
                "script: {}\ncases:\n  - name: c\n    scene: {}\n    params: {{attacker: 4, target: 2}}\n{rest}",
                root.join("accident.rhai").display(),
                root.join("scenes/highway.yaml").display()
            ),
        )
        .unwrap();
        run_test_file(&t)
    }

    #[test]
    fn a_candidate_that_cannot_be_read_is_the_test_file_s_fault_not_the_script_s() {
        // Both a scene and a rollout ran the script and failed as "accident.rhai: trajectories
        // do not fit the scene: candidate: give scene or rollout, not both"; an unreadable
        // rollout was blamed on the script the same way.
        let dir = tempfile::tempdir().unwrap();
        let e = accident_case(
            dir.path(),
            "    candidate: {scene: a.yaml, rollout: b.json}\n    expect: {total_below: 1}\n",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("x.test.yaml: case \"c\": candidate: give `scene` or `rollout`, not both"),
            "{e}"
        );
        let r = accident_case(
            dir.path(),
            "    candidate: {rollout: /dev/zero}\n    expect: {total_below: 1}\n",
        )
        .unwrap();
        assert!(
            !r[0].passed
                && r[0]
                    .detail
                    .starts_with("case could not run: candidate.rollout: /dev/zero: ")
                && !r[0].detail.contains("accident.rhai"),
            "{}",
            r[0].detail
        );
    }

    #[test]
    fn expectations_that_cannot_fail_or_pass_are_refused_before_the_case_runs() {
        // `total_below: .inf` passed whatever the script did, `.nan` failed whatever it did,
        // a zero direction gave a NaN descent, an empty `error` matched every message.
        let dir = tempfile::tempdir().unwrap();
        for (expect, want) in [
            (
                "{total_below: .inf}",
                "`total_below` is inf: a threshold is a finite number",
            ),
            ("{total_above: .nan}", "`total_above` is NaN"),
            (
                "{terms_below: {contact: -.inf}}",
                "`terms_below.contact` is -inf",
            ),
            (
                "{terms_above: {contact: .nan}}",
                "`terms_above.contact` is NaN",
            ),
            (
                "{towards: {agent: 4, direction: [0, 0]}}",
                "`towards.direction` is [0, 0]: a direction is two finite numbers, not both 0",
            ),
            ("{error: \"\"}", "`error` is empty"),
            // The threshold was never looked at, and the case passed.
            (
                "{error: \"unknown agent\", total_below: -5}",
                "`error` expects the script to fail, so nothing else given beside it can be checked",
            ),
            (
                "{towards: {agent: 4, direction: [1e308, 1e308]}}",
                "`towards.direction` is [1e308, 1e308]: its length is out of range",
            ),
            (
                "{towards: {agent: 4, direction: [1e-200, 0]}}",
                "`towards.direction` is [1e-200, 0]: its length is out of range",
            ),
            (
                "{allows: {collide: [[2, 4], [4, 4]]}}",
                "`allows.collide` pairs agent 4 with itself",
            ),
        ] {
            let e = accident_case(dir.path(), &format!("    expect: {expect}\n"))
                .unwrap_err()
                .to_string();
            assert!(
                e.contains("x.test.yaml: case \"c\": expect: ") && e.contains(want),
                "{expect}: {e}"
            );
        }
    }

    #[test]
    fn an_edit_after_the_horizon_or_an_allowance_for_an_absent_agent_is_an_error() {
        // The edit changed nothing and the case passed on the unedited future; an absent agent
        // in `allows` failed as "FAILED allows exactly reverse [424242]".
        let dir = tempfile::tempdir().unwrap();
        let r = accident_case(
            dir.path(),
            "    edits: [{agent: 4, shift: [5, 0], from: 1e9}]\n    expect: {total_above: 10}\n",
        )
        .unwrap();
        assert!(
            !r[0].passed
                && r[0].detail.contains(
                    "case could not run: edit of agent 4 starts 1e9 s after the current step, \
                     after the last future step (7 s)"
                )
                && r[0].detail.contains("it changes nothing"),
            "{}",
            r[0].detail
        );
        let r = accident_case(
            dir.path(),
            "    expect: {allows: {collide: [[4, 2]], reverse: [424242]}}\n",
        )
        .unwrap();
        assert!(
            !r[0].passed && r[0].detail.contains("allows: no agent 424242"),
            "{}",
            r[0].detail
        );
    }

    #[test]
    fn an_expected_error_is_matched_in_the_message_not_in_the_script_s_name() {
        // Every message begins with the script's path: `error: "accident"` (or ".rhai")
        // passed for whatever error accident.rhai raised.
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts");
        let dir = tempfile::tempdir().unwrap();
        let t = dir.path().join("x.test.yaml");
        let case = |want: &str| {
            std::fs::write(
                &t,
                format!(
                    "script: {}\ncases:\n  - name: c\n    scene: {}\n    params: {{attacker: 4, target: 424242}}\n    expect: {{error: {want:?}}}\n",
                    root.join("accident.rhai").display(),
                    root.join("scenes/highway.yaml").display()
                ),
            )
            .unwrap();
            run_test_file(&t).unwrap().remove(0)
        };
        for want in ["accident", ".rhai", "scripts/"] {
            let r = case(want);
            assert!(!r.passed, "{want}: {}", r.detail);
        }
        let r = case("424242");
        assert!(r.passed, "{}", r.detail);
    }

    #[test]
    fn a_blank_case_name_is_refused_naming_the_case() {
        let dir = tempfile::tempdir().unwrap();
        let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts");
        for name in ["''", "'   '"] {
            let t = dir.path().join("x.test.yaml");
            std::fs::write(
                &t,
                format!(
                    "script: {}\ncases:\n  - name: {name}\n    scene: {}\n    params: {{attacker: 4, target: 2}}\n    expect: {{total_above: 0}}\n",
                    root.join("accident.rhai").display(),
                    root.join("scenes/highway.yaml").display()
                ),
            )
            .unwrap();
            let e = run_test_file(&t).unwrap_err().to_string();
            assert!(
                e.contains("x.test.yaml: cases[0]: the name") && e.contains("is blank"),
                "{name}: {e}"
            );
        }
    }

    #[test]
    fn a_parameter_given_as_a_list_or_map_is_named_as_such() {
        // Read as the word "a: 1" (or refused for the line break in "- 2\n- 3").
        let dir = tempfile::tempdir().unwrap();
        for (value, kind) in [
            ("{a: 1}", "a map"),
            ("[4, 5]", "a list"),
            ("~", "nothing (null)"),
        ] {
            let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts");
            let t = dir.path().join("x.test.yaml");
            std::fs::write(
                &t,
                format!(
                    "script: {}\ncases:\n  - name: c\n    scene: {}\n    params: {{attacker: {value}, target: 2}}\n    expect: {{total_above: 0}}\n",
                    root.join("accident.rhai").display(),
                    root.join("scenes/highway.yaml").display()
                ),
            )
            .unwrap();
            let e = run_test_file(&t).unwrap_err().to_string();
            assert!(
                e.contains(&format!(
                    "x.test.yaml: case \"c\": params.attacker: is {kind}; a parameter is"
                )),
                "{value}: {e}"
            );
        }
    }

    #[test]
    fn a_sway_starts_at_its_from_like_every_edit() {
        // The sway began at the current step whatever `from` said: one starting after the
        // last future step passed as a swaying candidate.
        let dir = tempfile::tempdir().unwrap();
        let r = accident_case(
            dir.path(),
            "    edits: [{agent: 4, sway: [3, 2], from: 1e9}]\n    expect: {total_above: 10}\n",
        )
        .unwrap();
        assert!(
            !r[0].passed && r[0].detail.contains("starts 1e9 s after the current step"),
            "{}",
            r[0].detail
        );
        let mut edit = Edit {
            agent: 1,
            lateral: None,
            shift: None,
            freeze: false,
            sway: Some([1.0, 4.0]),
            from: 2.0,
            ramp: 0.0,
        };
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        let scene = load_scene(&p, 0, &LoadOptions::default()).unwrap();
        let recorded = Trajectories::recorded(&scene);
        let mut traj = recorded.clone();
        apply_edit(&scene, &mut traj, &edit).unwrap();
        let dt = scene.meta.dt;
        let a = scene.agents.iter().position(|x| x.id == 1).unwrap();
        let n = traj.layout.steps;
        let moved = |traj: &Trajectories, k: usize| {
            let (p, q) = (traj.xyh[a * n + k], recorded.xyh[a * n + k]);
            (p[0] - q[0]).hypot(p[1] - q[1])
        };
        let before = ((2.0 / dt) as usize).saturating_sub(2);
        assert_eq!(moved(&traj, before), 0.0);
        assert!((0..n).any(|k| moved(&traj, k) > 0.5));
        edit.from = 0.0;
        let mut now = recorded.clone();
        apply_edit(&scene, &mut now, &edit).unwrap();
        assert!(moved(&now, before) > 0.0);
    }

    #[cfg(unix)]
    #[test]
    fn a_link_loop_in_a_test_directory_is_walked_once() {
        // `ln -s . loop` found (and ran, and counted) every test 41 times; a second such link
        // made it 2^40 and never finished.
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("a.test.yaml"), "").unwrap();
        std::os::unix::fs::symlink(".", dir.path().join("loop")).unwrap();
        let found = find_test_files(&[dir.path().to_path_buf()]).unwrap();
        assert_eq!(found, vec![dir.path().join("a.test.yaml")]);
    }

    #[test]
    fn allows_must_match_the_script_s_exemptions_exactly() {
        let acc = "{attacker: 4, target: 2}";
        let pass = case("accident.rhai", acc, "{allows: {collide: [[2, 4]]}}");
        assert!(pass.passed, "{}", pass.detail);
        assert!(pass.detail.contains("collide [[2, 4]]"), "{}", pass.detail);
        for wrong in [
            "{allows: {collide: [[2, 3]]}}",
            "{allows: {collide: [[2, 4]], reverse: [4]}}",
            "{allows: {}}",
        ] {
            let r = case("accident.rhai", acc, wrong);
            assert!(
                !r.passed && r.detail.contains("FAILED allows"),
                "{wrong}: {}",
                r.detail
            );
        }
        let rev = case("reverse.rhai", "{vehicle: 4}", "{allows: {reverse: [4]}}");
        assert!(rev.passed, "{}", rev.detail);
        let none = case(
            "speed_limit.rhai",
            "{vehicle: 1}",
            "{allows: {reverse: [1]}}",
        );
        assert!(!none.passed, "{}", none.detail);
    }
}
