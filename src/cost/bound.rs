//! A cost script bound to one scene that any thread may evaluate: what a host that calls from
//! several threads (the Python package, a planner's worker pool) holds.
//!
//! A [`CostScript`] is single-threaded (its Rhai engine and scene are reference-counted), so
//! a [`BoundScript`] keeps only what compiles it (a [`ScriptSpec`] and the scene) and each
//! thread compiles its own copy on first use, kept in a small per-thread cache. A batch runs
//! on rayon's pool, whose threads live on, so a script is compiled once per core, not once per
//! call.

use std::cell::RefCell;
use std::rc::Rc;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::Arc;
use std::time::Duration;

use rayon::prelude::*;

use super::engine::{CostError, CostScript};
use super::report::CostReport;
use super::spec::ScriptSpec;
use super::trajectory::{Trajectories, VarLayout};
use crate::scene::Scene;

/// Compiled scripts a thread keeps: enough for a handful of scripts on a handful of scenes
/// at once; the least recently used one goes first.
const PER_THREAD: usize = 16;

static NEXT_ID: AtomicU64 = AtomicU64::new(1);

/// The stack of a thread that evaluates scripts. Rhai walks the arrays and maps a script
/// builds recursively, with no limit on their depth but the array limit's (each level is an
/// element: 100,000 levels by default): to check their sizes, copy and drop them (about 260
/// bytes a level), and to compare and print them (`a == b`, `contains`, `index_of`, `dedup`,
/// `print`: up to 2 KB a level). A main thread's 8 MB overflowed at 5,000 levels, which
/// `a = [a]` in a loop reaches in a second, and a thread of rayon's pool's 2 MB at 1,000: the
/// process aborted ("stack overflow"), Python's interpreter with it. 256 MB holds the deepest
/// array the default limits allow; it is address space, used only as deep as a script goes.
pub const SCRIPT_STACK_BYTES: usize = 256 << 20;

/// Runs `f` on a thread of the pool that evaluates batches, which has the stack scripts need
/// ([`SCRIPT_STACK_BYTES`]), and returns what it returns: for a host whose own threads have
/// less (Python's), wherever a script runs. The pool's threads live on, so the scripts
/// they compile are kept for the next call.
pub fn on_script_stack<R: Send>(f: impl FnOnce() -> R + Send) -> R {
    match pool() {
        Some(p) => p.install(f),
        None => f(),
    }
}

/// The pool that evaluates batches: rayon's own, but with [`SCRIPT_STACK_BYTES`] of stack per
/// thread (`None` where it cannot be made: the global pool is used), one per process. A
/// process forked from one that had made it (Python's `multiprocessing` on Linux, a PyTorch
/// DataLoader's workers) holds the pool's memory but none of its threads: every evaluation
/// there waited for them forever. It makes a pool of its own (the parent's copy, whose
/// threads it never had, is left as it is).
fn pool() -> Option<&'static rayon::ThreadPool> {
    type Made = (u32, Option<&'static rayon::ThreadPool>);
    static POOL: std::sync::Mutex<Option<Made>> = std::sync::Mutex::new(None);
    let pid = std::process::id();
    let mut made = POOL.lock().unwrap_or_else(|p| p.into_inner());
    match *made {
        Some((owner, pool)) if owner == pid => pool,
        _ => {
            let pool = rayon::ThreadPoolBuilder::new()
                .stack_size(SCRIPT_STACK_BYTES)
                .thread_name(|i| format!("drivescript-script-{i}"))
                .build()
                .ok()
                .map(|p| &*Box::leak(Box::new(p)));
            *made = Some((pid, pool));
            pool
        }
    }
}

thread_local! {
    static COMPILED: RefCell<Vec<(u64, Rc<CostScript>)>> = const { RefCell::new(Vec::new()) };
}

/// A [`ScriptSpec`] compiled and validated against one scene, evaluable from any thread
/// (`Send + Sync`).
#[derive(Debug)]
pub struct BoundScript {
    id: u64,
    spec: ScriptSpec,
    scene: Arc<Scene>,
    validated: Duration,
}

impl BoundScript {
    /// Compiles `spec` against `scene` and validates it ([`CostScript::validate`]: the dry
    /// run `drivescript cost` makes before it evaluates), on the calling thread.
    pub fn new(spec: ScriptSpec, scene: Scene) -> Result<Self, CostError> {
        let mut bound = Self {
            id: NEXT_ID.fetch_add(1, Ordering::Relaxed),
            spec,
            scene: Arc::new(scene),
            validated: Duration::ZERO,
        };
        bound.validated = bound.with_script(|s| s.validate())??.elapsed;
        Ok(bound)
    }

    /// The scene the script is bound to.
    pub fn scene(&self) -> &Scene {
        &self.scene
    }

    /// What the script was compiled from.
    pub fn spec(&self) -> &ScriptSpec {
        &self.spec
    }

    /// The layout of the trajectories it takes: the scene's agents by its future steps.
    pub fn layout(&self) -> VarLayout {
        VarLayout::of(&self.scene)
    }

    /// How long the validation run took.
    pub fn validated_in(&self) -> Duration {
        self.validated
    }

    /// The terms no probe moves ([`CostScript::dead_terms`]): what `drivescript cost` warns
    /// about after validating.
    pub fn dead_terms(&self) -> Result<Vec<super::engine::DeadTerm>, CostError> {
        self.with_script(|s| s.dead_terms())
    }

    /// Evaluates every term and its gradient on `traj` ([`CostScript::evaluate`]).
    pub fn evaluate(&self, traj: &Trajectories) -> Result<CostReport, CostError> {
        self.with_script(|s| s.evaluate(traj))?
    }

    /// Evaluates each of `trajs` in parallel on rayon's pool: the reports in order, or the
    /// first (lowest-index) item that fails, with its index. Items after a failure are not
    /// started: a script slow on every item (up to its wall-time limit each) held a batch of
    /// 1,000 for 40 minutes on two cores to report one error.
    pub fn evaluate_batch(
        &self,
        trajs: &[Trajectories],
    ) -> Result<Vec<CostReport>, (usize, CostError)> {
        let never = AtomicBool::new(false);
        self.evaluate_batch_until(trajs, &never)
            .expect("a batch nobody stops runs to its end")
    }

    /// [`evaluate_batch`](Self::evaluate_batch) that another thread may stop by setting
    /// `stop` (Python's Ctrl-C): items not begun by then are not started, and the answer is
    /// `None`. A batch of 200,000 items ran its 45 s to the end after a Ctrl-C.
    pub fn evaluate_batch_until(
        &self,
        trajs: &[Trajectories],
        stop: &AtomicBool,
    ) -> Option<Result<Vec<CostReport>, (usize, CostError)>> {
        let failed = std::sync::atomic::AtomicUsize::new(usize::MAX);
        let run = || -> Vec<Option<Result<CostReport, CostError>>> {
            trajs
                .par_iter()
                .enumerate()
                .map(|(k, t)| {
                    // An earlier item has failed: its error is the one reported.
                    if k > failed.load(Ordering::Relaxed) || stop.load(Ordering::Relaxed) {
                        return None;
                    }
                    let r = self.evaluate(t);
                    if r.is_err() {
                        failed.fetch_min(k, Ordering::Relaxed);
                    }
                    Some(r)
                })
                .collect()
        };
        let results = match pool() {
            Some(p) => p.install(run),
            None => run(),
        };
        let mut out = Vec::with_capacity(results.len());
        for (k, r) in results.into_iter().enumerate() {
            match r {
                Some(Ok(report)) => out.push(report),
                Some(Err(e)) => return Some(Err((k, e))),
                // Skipped after an earlier failure (which the loop has returned) or a stop.
                None => {
                    assert!(
                        stop.load(Ordering::Relaxed),
                        "item {k} skipped with no failure before it"
                    );
                    return None;
                }
            }
        }
        Some(Ok(out))
    }

    /// Runs `f` on this thread's compiled copy, compiling it first when the thread has none.
    fn with_script<R>(&self, f: impl FnOnce(&CostScript) -> R) -> Result<R, CostError> {
        let cached = COMPILED.with(|c| {
            let mut c = c.borrow_mut();
            let at = c.iter().position(|(id, _)| *id == self.id)?;
            let hit = c.remove(at);
            let script = hit.1.clone();
            c.push(hit);
            Some(script)
        });
        let script = match cached {
            Some(s) => s,
            None => {
                let s = Rc::new(self.spec.compile(Rc::new((*self.scene).clone()))?);
                COMPILED.with(|c| {
                    let mut c = c.borrow_mut();
                    if c.len() >= PER_THREAD {
                        c.remove(0);
                    }
                    c.push((self.id, s.clone()));
                });
                s
            }
        };
        // The cache is not borrowed while the script runs.
        Ok(f(&script))
    }
}

impl Drop for BoundScript {
    /// Frees this thread's copy at once; other threads' copies age out of their caches.
    fn drop(&mut self) {
        let _ = COMPILED.try_with(|c| {
            if let Ok(mut c) = c.try_borrow_mut() {
                c.retain(|(id, _)| *id != self.id);
            }
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::cost::Params;

    fn scene() -> Scene {
        crate::cost::gradient_tests::sample(crate::cost::gradient_tests::US101)
    }

    fn cut_in() -> ScriptSpec {
        ScriptSpec::from_file(
            std::path::Path::new(concat!(env!("CARGO_MANIFEST_DIR"), "/scripts/cut_in.rhai")),
            Params::numbers(&[("cutter", 401.0), ("victim", 405.0)]),
        )
        .unwrap()
    }

    #[test]
    fn a_batch_on_the_pool_equals_one_by_one_on_this_thread() {
        let scene = scene();
        let direct = cut_in().compile(Rc::new(scene.clone())).unwrap();
        let bound = BoundScript::new(cut_in(), scene.clone()).unwrap();
        let mut trajs = Vec::new();
        for k in 0..8 {
            let mut t = Trajectories::recorded(&scene);
            for s in &mut t.xyh {
                s[0] += 0.25 * k as f64;
            }
            trajs.push(t);
        }
        let batch = bound.evaluate_batch(&trajs).unwrap();
        assert_eq!(batch.len(), trajs.len());
        for (t, got) in trajs.iter().zip(batch) {
            let want = direct.evaluate(t).unwrap();
            assert_eq!(got.total, want.total);
            assert_eq!(got.gradient, want.gradient);
        }
        // The trajectories differ, so must their costs: the pool did not evaluate one of them
        // for all.
        let totals: Vec<f64> = trajs
            .iter()
            .map(|t| bound.evaluate(t).unwrap().total)
            .collect();
        assert!(totals.windows(2).any(|w| w[0] != w[1]), "{totals:?}");
    }

    #[test]
    fn a_batch_reports_its_first_failure_without_running_the_rest_to_their_limits() {
        // Fast on the log (so it validates), a busy loop to the wall-time limit on any
        // trajectory that moves agent 401 100 km away.
        let src = "let x = agent(401).x;\nlet n = if value(x.max()) > 1.0e5 { 100000000 } else { 0 };\nlet s = 0.0;\nfor i in 0..n { s += 1.0; }\nterm(\"t\", x.mean() + s);";
        let mut spec = ScriptSpec::new(src, "slow.rhai", Params::default());
        spec.limits = crate::cost::Limits {
            wall_time: Duration::from_millis(300),
            max_operations: u64::MAX,
            ..Default::default()
        };
        let scene = scene();
        let bound = BoundScript::new(spec, scene.clone()).unwrap();
        let i401 = scene.agents.iter().position(|a| a.id == 401).unwrap();
        let slow = {
            let mut t = Trajectories::recorded(&scene);
            let n = t.layout.steps;
            for s in &mut t.xyh[i401 * n..(i401 + 1) * n] {
                s[0] += 2.0e5;
            }
            t
        };
        let fast = Trajectories::recorded(&scene);
        let mut trajs = vec![fast.clone(), slow.clone()];
        trajs.extend(std::iter::repeat_n(slow, 40));
        let t0 = std::time::Instant::now();
        let (k, e) = match bound.evaluate_batch(&trajs) {
            Ok(r) => panic!("no item of {} failed", r.len()),
            Err(failed) => failed,
        };
        // 40 slow items at 0.3 s each took 6 s on two cores before; now the ones started
        // beside the first failure finish, the rest are skipped.
        assert!(t0.elapsed() < Duration::from_secs(3), "{:?}", t0.elapsed());
        assert_eq!(k, 1, "{e}");
        assert!(e.to_string().contains("wall time"), "{e}");
    }

    #[test]
    fn a_batch_stopped_from_another_thread_starts_no_more_items() {
        // Each item busy for about 50 ms: 400 of them take 10 s on two cores unless stopped.
        let src = "let x = agent(401).x;\nlet s = 0.0;\nfor i in 0..200000 { s += 1.0; }\nterm(\"t\", x.mean() + s * 0.0);";
        let mut spec = ScriptSpec::new(src, "slow.rhai", Params::default());
        spec.limits = crate::cost::Limits {
            max_operations: u64::MAX,
            ..Default::default()
        };
        let scene = scene();
        let bound = BoundScript::new(spec, scene.clone()).unwrap();
        let trajs = vec![Trajectories::recorded(&scene); 400];
        let stop = AtomicBool::new(false);
        let t0 = std::time::Instant::now();
        let got = std::thread::scope(|s| {
            let run = s.spawn(|| bound.evaluate_batch_until(&trajs, &stop));
            std::thread::sleep(Duration::from_millis(200));
            stop.store(true, Ordering::Relaxed);
            run.join().unwrap()
        });
        assert!(got.is_none());
        assert!(t0.elapsed() < Duration::from_secs(3), "{:?}", t0.elapsed());
        // A batch nobody stops is whole.
        let few = &trajs[..3];
        assert_eq!(bound.evaluate_batch(few).unwrap().len(), 3);
    }

    #[test]
    fn a_script_bound_to_two_scenes_keeps_them_apart() {
        let scene = scene();
        let short = scene.over_horizon(20);
        let long = BoundScript::new(cut_in(), scene.clone()).unwrap();
        let cut = BoundScript::new(cut_in(), short.clone()).unwrap();
        assert_eq!(cut.layout().steps, 20);
        assert_eq!(long.layout().steps, scene.num_future_steps());
        assert!(cut.evaluate(&Trajectories::recorded(&short)).is_ok());
        let wrong = cut.evaluate(&Trajectories::recorded(&scene)).unwrap_err();
        assert!(matches!(wrong, CostError::Shape { .. }), "{wrong}");
    }

    #[test]
    fn validation_errors_come_from_new_with_the_script_s_line() {
        let spec = ScriptSpec::new("term(\"flat\", 1.0);", "flat.rhai", Params::default());
        let e = BoundScript::new(spec, scene()).unwrap_err();
        assert!(
            e.to_string().starts_with("flat.rhai:1: term \"flat\""),
            "{e}"
        );
    }

    #[test]
    fn a_bound_script_moves_to_another_thread_and_evaluates_there() {
        let scene = scene();
        let bound = Arc::new(BoundScript::new(cut_in(), scene.clone()).unwrap());
        let here = bound.evaluate(&Trajectories::recorded(&scene)).unwrap();
        let b = bound.clone();
        let there = std::thread::spawn(move || {
            let t = Trajectories::recorded(b.scene());
            b.evaluate(&t).unwrap().total
        })
        .join()
        .unwrap();
        assert_eq!(there, here.total);
    }
}
