//! The sandboxed Rhai engine: compile → validate → evaluate.
//!
//! Scripts are untrusted (an LLM wrote them). The engine starts from `Engine::new_raw()` with
//! only arithmetic, logic, strings, iteration, function pointers, arrays, maps and math: no
//! file, network, process, environment, time or `eval`, no `sleep` or `exit`. `import` resolves
//! only the modules under `stdlib/` (embedded at build time). Operations, call depth,
//! expression depth, string, array and map sizes, variables, modules and wall time are all
//! limited, and each breach is an error naming the limit and the script line.

use std::cell::{Cell, RefCell};
use std::collections::HashMap;
use std::rc::Rc;
use std::time::{Duration, Instant};

use rhai::packages::{
    ArithmeticPackage, BasicArrayPackage, BasicFnPackage, BasicIteratorPackage, BasicMapPackage,
    BasicMathPackage, BasicStringPackage, LogicPackage, MoreStringPackage, Package,
};
use rhai::{
    Dynamic, Engine, EvalAltResult, Module, NativeCallContext, ParseErrorType, Position, Scope, AST,
};

use super::dual::Dual;
use super::params::{ParamValue, Params};
use super::report::{CostReport, TermReport};
use super::series::Series;
use super::stdlib::{self, Ctx, DocEntry, Shared, Term};
use super::trajectory::{Trajectories, VarLayout};
use crate::scene::Scene;

/// The Rhai modules of `stdlib/`, embedded so that the binary needs no files at run time.
pub const STDLIB_MODULES: &[(&str, &str)] =
    &[("behaviours", include_str!("../../stdlib/behaviours.rhai"))];

/// Resource limits for one script. Every field is configurable; the defaults suit scripts of
/// a few dozen lines evaluated at every diffusion step.
#[derive(Debug, Clone, PartialEq)]
pub struct Limits {
    /// Rhai operations per evaluation.
    pub max_operations: u64,
    /// Nested function calls.
    pub max_call_levels: usize,
    /// Expression nesting at the top level.
    pub max_expr_depth: usize,
    /// Expression nesting inside functions.
    pub max_fn_expr_depth: usize,
    /// Characters in a string.
    pub max_string_size: usize,
    /// Elements in an array.
    pub max_array_size: usize,
    /// Entries in a map.
    pub max_map_size: usize,
    /// Variables alive at once.
    pub max_variables: usize,
    /// Imported modules.
    pub max_modules: usize,
    /// Wall time per evaluation.
    pub wall_time: Duration,
    /// Lines kept from `print`.
    pub max_print_lines: usize,
    /// Bytes of source: checked before compiling, because Rhai's parser takes time quadratic
    /// in the number of distinct variables (20,000 `let`s took 8 s to reach the variables
    /// limit, 100,000 did not finish in a minute).
    pub max_source_bytes: usize,
    /// Bytes of series (values and gradients) alive at once, checked as the script runs: the
    /// wall clock alone let a nine-line script hold gigabytes and abort the process.
    pub max_series_bytes: usize,
    /// Bytes the process may grow by during one evaluation, read from the operating system
    /// every few milliseconds of an evaluation that runs that long (Linux; not checked
    /// elsewhere): arrays and maps of copies (`a[i] = s` of a large `s`) hold more than the
    /// size limits, which count an assigned item alone, let through.
    pub max_memory_growth: usize,
}

impl Default for Limits {
    fn default() -> Self {
        Self {
            max_operations: 2_000_000,
            max_call_levels: 32,
            max_expr_depth: 64,
            max_fn_expr_depth: 32,
            max_string_size: 10_000,
            max_array_size: 100_000,
            max_map_size: 10_000,
            max_variables: 1_000,
            max_modules: 8,
            wall_time: Duration::from_secs(5),
            max_print_lines: 200,
            // The largest hand-written script is under 2 KB; 64 KB of the worst case
            // compiles in a fraction of a second.
            max_source_bytes: MAX_SOURCE_BYTES,
            // The hand-written scripts hold a few MB on the largest scenes.
            max_series_bytes: 512 << 20,
            // Above the series limit, which the growth includes.
            max_memory_growth: 1 << 30,
        }
    }
}

/// The default [`Limits::max_source_bytes`], also the most a script file read from disk may
/// hold.
pub const MAX_SOURCE_BYTES: usize = 64 << 10;

/// Reads a cost script file: a regular file of at most [`MAX_SOURCE_BYTES`] in UTF-8 (a FIFO
/// or a device is refused before it is read: it could block or never end).
pub fn read_script(path: &std::path::Path) -> Result<String, CostError> {
    crate::io::read_regular_text(path, MAX_SOURCE_BYTES as u64, "a cost script")
        .map_err(|e| CostError::Read(e.to_string()))
}

/// `script:line:column`, as far as they are known (0 is unknown): a limit reached where Rhai
/// gives no position, or a total no one line makes, printed `m.rhai:0:0`, which points at no
/// line of the file.
fn place(script: &str, line: usize, column: usize) -> String {
    let script = one_line(script);
    match (line, column) {
        (0, _) => script,
        (l, 0) => format!("{script}:{l}"),
        (l, c) => format!("{script}:{l}:{c}"),
    }
}

/// A script's name (its path, for a file) on one line: a file named `a\nerror: all good.rhai`
/// began every message of the script with a line of its own.
fn one_line(script: &str) -> String {
    crate::io::name::one_line(script)
}

/// Errors from compiling, validating or evaluating a cost script. Each names the script and,
/// where there is one, the line and column.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CostError {
    /// The script does not parse.
    #[error("{}: syntax error: {message}", place(.script, *.line, *.column))]
    Syntax {
        /// Script name.
        script: String,
        /// Line (1-based).
        line: usize,
        /// Column (1-based).
        column: usize,
        /// What is wrong.
        message: String,
    },
    /// Evaluation failed.
    #[error("{}: {message}", place(.script, *.line, *.column))]
    Runtime {
        /// Script name.
        script: String,
        /// Line (0 when unknown).
        line: usize,
        /// Column.
        column: usize,
        /// What went wrong.
        message: String,
    },
    /// A resource limit was reached.
    #[error("{}: limit exceeded: {limit}", place(.script, *.line, *.column))]
    Limit {
        /// Script name.
        script: String,
        /// Which limit and its value.
        limit: String,
        /// Line (0 when unknown).
        line: usize,
        /// Column (0 when unknown).
        column: usize,
    },
    /// A term is unusable as a guidance cost.
    #[error("{}: term {term:?}: {message}", place(.script, *.line, 0))]
    Term {
        /// Script name.
        script: String,
        /// Term name.
        term: String,
        /// Line of its declaration.
        line: usize,
        /// What is wrong.
        message: String,
    },
    /// The scene has no step after its current one: there is no future to score or guide.
    #[error("{}: scene {scene} has no step after its current step {current}: there is no future to score", one_line(.script))]
    NoFuture {
        /// Script name.
        script: String,
        /// The scene's id.
        scene: String,
        /// Its current step (its last).
        current: usize,
    },
    /// The script declared nothing.
    #[error("{}: the script declares no term; call term(name, value) at least once", one_line(.script))]
    NoTerms {
        /// Script name.
        script: String,
    },
    /// A `--param` that cannot be used.
    #[error("parameter \"{name}\": {message}")]
    Param {
        /// Parameter name (or the whole argument), as [`crate::io::name::shown`] quotes it.
        name: String,
        /// What is wrong.
        message: String,
    },
    /// The script file cannot be read (the message names it).
    #[error("{0}")]
    Read(String),
    /// Trajectories that do not belong to the scene.
    #[error("{}: trajectories do not fit the scene: {message}", one_line(.script))]
    Shape {
        /// Script name.
        script: String,
        /// What does not fit.
        message: String,
    },
}

/// A term no probe moves ([`CostScript::dead_terms`]): a zero gradient on the recorded future
/// and on every perturbed one, so it can never steer sampling.
#[derive(Debug, Clone, PartialEq)]
pub struct DeadTerm {
    /// The script that declares it.
    pub script: String,
    /// Its name.
    pub term: String,
    /// Line of its `term(...)` call.
    pub line: usize,
    /// A value other than 0 it took on some probe (a constant, a saturated sigmoid); `None`
    /// where it was 0 on every one.
    pub value: Option<f64>,
    /// Its weight, where the weight alone stills it: the value moved on some probe, but
    /// weighted by 0 (or a weight so small that the product is 0 in the sampler's single
    /// precision) it steers nothing.
    pub weighted_out: Option<f64>,
}

impl DeadTerm {
    /// Why it cannot steer, and what to do, in words (without the script, line and term).
    pub fn message(&self) -> String {
        let probes = format!(
            "on the recorded future and on {} perturbed ones ({})",
            super::probe::PROBES.len(),
            super::probe::PROBES.join(", ")
        );
        if let Some(w) = self.weighted_out {
            // A weight of 0 (or 1e-320) was taken without a word: the term was reported and
            // judged against its tolerance, yet could never move a sample towards it.
            return format!(
                "its weight, {}, makes its gradient 0 {probes}, though its value follows the \
                 motion, so it can never steer sampling: give it a weight above 0 (1 is the \
                 default), or drop the term",
                crate::geom::num(w)
            );
        }
        match self.value {
            None => format!(
                "it is 0 with a zero gradient {probes}, so it can never steer sampling: a term \
                 must grow as the motion departs from what is asked (a relu whose threshold no \
                 plausible motion reaches, or anything times 0, is always 0)"
            ),
            // `1.0 + 0.0 * a.x.last()` or `sigmoid(a.x, 1e308)` passed validation without a
            // word: not 0, but no more able to steer than a term that is.
            Some(v) => format!(
                "its gradient is zero {probes} (its value, {}, does not follow the motion), so \
                 it can never steer sampling: a term must grow as the motion departs from what \
                 is asked (a constant, a step or a saturated sigmoid does not)",
                crate::geom::num(v)
            ),
        }
    }

    /// As a validation error, for callers that refuse such a term (the LLM loop).
    pub fn to_error(&self) -> CostError {
        CostError::Term {
            script: self.script.clone(),
            term: self.term.clone(),
            line: self.line,
            message: self.message(),
        }
    }
}

impl std::fmt::Display for DeadTerm {
    /// `script:line: term "name": it is 0 ...`, as validation errors read.
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        write!(f, "{}", self.to_error())
    }
}

/// Only the embedded stdlib modules, by bare name.
struct StdlibResolver {
    cache: RefCell<HashMap<String, rhai::Shared<Module>>>,
}

impl rhai::ModuleResolver for StdlibResolver {
    fn resolve(
        &self,
        engine: &Engine,
        _source: Option<&str>,
        path: &str,
        pos: Position,
    ) -> Result<rhai::Shared<Module>, Box<EvalAltResult>> {
        if let Some(m) = self.cache.borrow().get(path) {
            return Ok(m.clone());
        }
        let names: Vec<&str> = STDLIB_MODULES.iter().map(|(n, _)| *n).collect();
        let Some((_, src)) = STDLIB_MODULES.iter().find(|(n, _)| *n == path) else {
            return Err(Box::new(EvalAltResult::ErrorModuleNotFound(
                format!(
                    "{path} (only the stdlib modules {} can be imported)",
                    names.join(", ")
                ),
                pos,
            )));
        };
        let mut ast = engine.compile(src).map_err(|e| {
            Box::new(EvalAltResult::ErrorInModule(
                path.into(),
                Box::new(e.into()),
                pos,
            ))
        })?;
        ast.set_source(format!("stdlib/{path}.rhai"));
        let m = Module::eval_ast_as_new(Scope::new(), &ast, engine)
            .map_err(|e| Box::new(EvalAltResult::ErrorInModule(path.into(), e, pos)))?;
        let m: rhai::Shared<Module> = m.into();
        self.cache.borrow_mut().insert(path.into(), m.clone());
        Ok(m)
    }
}

/// The parameters `source` names: `param("name"...)` calls, in order of first use.
pub fn script_params(source: &str) -> Vec<String> {
    let mut out: Vec<String> = Vec::new();
    let mut rest = source;
    while let Some(i) = rest.find("param(\"") {
        let after = &rest[i + 7..];
        let Some(q) = after.find('"') else { break };
        let name = after[..q].to_string();
        if !out.contains(&name) {
            out.push(name);
        }
        rest = &after[q..];
    }
    out
}

/// Words of the language: a parameter with one of these names can be read only by
/// `param("name")`, never as a constant.
const KEYWORDS: &[&str] = &[
    "let",
    "const",
    "fn",
    "if",
    "else",
    "switch",
    "do",
    "while",
    "until",
    "loop",
    "for",
    "in",
    "continue",
    "break",
    "return",
    "throw",
    "try",
    "catch",
    "import",
    "export",
    "as",
    "global",
    "private",
    "true",
    "false",
    "this",
    "is",
    "Fn",
    "call",
    "curry",
    "type_of",
    "print",
    "debug",
    "eval",
    "is_def_fn",
    "is_def_var",
    "is_shared",
];

/// Whether `source` uses `name` at all: as a string literal (what `param("name")` takes) or
/// as the constant `name` in code. Not in a comment (`// keep the margin` reads no `margin`),
/// nor as a keyword, a function's name (`term(`) or a property (`.speed`): each of those made
/// a mistyped `--param` look read, and the script ran with its default.
pub fn uses_param(source: &str, name: &str) -> bool {
    let b: Vec<char> = source.chars().collect();
    let ident = |c: char| c.is_alphanumeric() || c == '_';
    let (mut i, mut prev) = (0, None::<char>);
    while i < b.len() {
        let c = b[i];
        match (c, b.get(i + 1).copied()) {
            ('/', Some('/')) => {
                while i < b.len() && b[i] != '\n' {
                    i += 1;
                }
            }
            ('/', Some('*')) => {
                // Block comments nest.
                let mut depth = 0;
                while i < b.len() {
                    match (b[i], b.get(i + 1).copied()) {
                        ('/', Some('*')) => (depth, i) = (depth + 1, i + 2),
                        ('*', Some('/')) => (depth, i) = (depth - 1, i + 2),
                        _ => i += 1,
                    }
                    if depth == 0 {
                        break;
                    }
                }
            }
            ('"' | '`', _) => {
                let mut lit = String::new();
                i += 1;
                while i < b.len() && b[i] != c {
                    if b[i] == '\\' && c == '"' {
                        i += 1;
                    }
                    lit.extend(b.get(i));
                    i += 1;
                }
                i += 1;
                // A backtick string's `${...}` is code: read through, leniently.
                if lit == name || (c == '`' && uses_param(&lit, name)) {
                    return true;
                }
                prev = Some(c);
            }
            ('\'', _) => {
                i += if b.get(i + 1) == Some(&'\\') { 4 } else { 3 };
                prev = Some(c);
            }
            (c, _) if ident(c) => {
                let start = i;
                while i < b.len() && ident(b[i]) {
                    i += 1;
                }
                let word: String = b[start..i].iter().collect();
                let called = b[i..].iter().find(|c| !c.is_whitespace()) == Some(&'(');
                if word == name
                    && !c.is_ascii_digit()
                    && prev != Some('.')
                    && !called
                    && !KEYWORDS.contains(&name)
                {
                    return true;
                }
                prev = Some(b[i - 1]);
            }
            (c, _) => {
                if !c.is_whitespace() {
                    prev = Some(c);
                }
                i += 1;
            }
        }
    }
    false
}

/// `DT` and `STEPS` are the engine's constants, not parameters.
fn no_reserved(params: &Params) -> Result<(), CostError> {
    for reserved in ["DT", "STEPS"] {
        if params.get(reserved).is_some() {
            return Err(CostError::Param {
                name: reserved.into(),
                message:
                    "is a built-in constant (seconds per step, future steps) and cannot be set"
                        .into(),
            });
        }
    }
    Ok(())
}

/// Every parameter in `params` is read by one of `sources`: a name none uses is a typo
/// (`margn=30` would run with the default margin), an error listing the scripts' parameters.
pub fn check_params(sources: &[&str], params: &Params) -> Result<(), CostError> {
    no_reserved(params)?;
    for name in params.names() {
        if !sources.iter().any(|src| uses_param(src, name)) {
            let mut known: Vec<String> = Vec::new();
            for p in sources.iter().flat_map(|src| script_params(src)) {
                if !known.contains(&p) {
                    known.push(p);
                }
            }
            return Err(CostError::Param {
                name: name.to_string(),
                message: format!(
                    "no script reads it; {}",
                    if known.is_empty() {
                        "the scripts take no parameters".to_string()
                    } else {
                        format!("their parameters are {}", known.join(", "))
                    }
                ),
            });
        }
    }
    Ok(())
}

/// Marker returned by the progress callback when the wall time is up.
pub(crate) const WALL_TIME_MARK: &str = "drivescript:wall-time";
/// What `on_progress` stops a script with when its series outgrow [`Limits::max_series_bytes`].
pub(crate) const MEMORY_MARK: &str = "drivescript:memory";
/// What `on_progress` stops a script with past [`Limits::max_operations`] operations counted
/// by drivescript itself: Rhai counts the operations of a closure that a native function calls
/// (`map`, `filter`, `reduce`, `sort`, ...) on a copy of its counter, which is thrown away when
/// the closure returns, so that neither its limit nor a clock check every 512 of its
/// operations ever came: `r.map(|x| s.map(|y| y + 1).len())` over two 100,000-element arrays
/// ran for hours past the 5 s wall time.
pub(crate) const OPERATIONS_MARK: &str = "drivescript:operations";
/// What `on_progress` stops a script with when the process grows past
/// [`Limits::max_memory_growth`] during one evaluation.
pub(crate) const GROWTH_MARK: &str = "drivescript:growth";

/// A compiled cost script bound to a scene.
pub struct CostScript {
    name: String,
    engine: Engine,
    ast: AST,
    scope: Scope<'static>,
    shared: Shared,
    started: Rc<Cell<Instant>>,
    /// Operations of the evaluation under way, every one counted ([`OPERATIONS_MARK`]).
    ops: Rc<Cell<u64>>,
    limits: Limits,
    docs: Vec<DocEntry>,
    /// Evaluations so far and the time they took ([`CostScript::usage`]).
    used: Cell<Usage>,
}

/// What a compiled script's evaluations have cost so far: a sampling run checks the total
/// against its budget (`SampleConfig::script_budget`), since a script within the per-call
/// wall time can still take hours over the hundreds of evaluations of a run.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
pub struct Usage {
    /// Evaluations, finished or stopped.
    pub evaluations: u64,
    /// Wall time they took together.
    pub time: Duration,
}

impl Usage {
    /// The sum of two.
    pub fn plus(self, o: Usage) -> Usage {
        Usage {
            evaluations: self.evaluations.saturating_add(o.evaluations),
            time: self.time.saturating_add(o.time),
        }
    }

    /// Mean time per evaluation (zero before the first).
    pub fn mean(&self) -> Duration {
        match u32::try_from(self.evaluations) {
            Ok(0) => Duration::ZERO,
            Ok(n) => self.time / n,
            Err(_) => Duration::from_secs_f64(self.time.as_secs_f64() / self.evaluations as f64),
        }
    }
}

/// A fresh sandboxed engine with the stdlib registered; returns it with its documentation.
fn build_engine(
    shared: &Shared,
    limits: &Limits,
    started: &Rc<Cell<Instant>>,
    ops: &Rc<Cell<u64>>,
) -> (Engine, Vec<DocEntry>) {
    let mut e = Engine::new_raw();
    for pkg in [
        ArithmeticPackage::new().as_shared_module(),
        LogicPackage::new().as_shared_module(),
        BasicStringPackage::new().as_shared_module(),
        MoreStringPackage::new().as_shared_module(),
        BasicIteratorPackage::new().as_shared_module(),
        BasicFnPackage::new().as_shared_module(),
        BasicArrayPackage::new().as_shared_module(),
        BasicMapPackage::new().as_shared_module(),
        BasicMathPackage::new().as_shared_module(),
    ] {
        e.register_global_module(pkg);
    }
    e.disable_symbol("eval");
    // Rhai reads `1e400` as infinity, which then surfaced as "weight inf must be finite", a
    // number the user never wrote.
    #[allow(deprecated)] // "volatile", not deprecated (Rhai's words)
    e.on_parse_token(|token, _, _| match token {
        rhai::Token::FloatConstant(f) if !f.0.is_finite() => rhai::Token::LexError(Box::new(
            rhai::LexError::Runtime(format!("the number {} {}", f.1, crate::geom::BEYOND_F64)),
        )),
        other => other,
    });
    e.set_strict_variables(true);
    e.set_max_operations(limits.max_operations)
        .set_max_call_levels(limits.max_call_levels)
        .set_max_expr_depths(limits.max_expr_depth, limits.max_fn_expr_depth)
        .set_max_string_size(limits.max_string_size)
        .set_max_array_size(limits.max_array_size)
        .set_max_map_size(limits.max_map_size)
        .set_max_variables(limits.max_variables)
        .set_max_modules(limits.max_modules);
    let (t0, wall, memory) = (started.clone(), limits.wall_time, limits.max_series_bytes);
    let (count, max_ops) = (ops.clone(), limits.max_operations);
    let (watch, growth) = (
        super::resident::GrowthWatch::default(),
        limits.max_memory_growth,
    );
    // Every operation is counted here, not by the number Rhai passes: see OPERATIONS_MARK.
    e.on_progress(move |_| {
        let ops = count.get() + 1;
        count.set(ops);
        if max_ops > 0 && ops > max_ops {
            Some(Dynamic::from(OPERATIONS_MARK.to_string()))
        } else if ops % 512 != 0 {
            // Checking the clock every operation would cost more than most scripts.
            None
        } else if t0.get().elapsed() > wall {
            Some(Dynamic::from(WALL_TIME_MARK.to_string()))
        } else if super::series::live_series_bytes() > memory {
            Some(Dynamic::from(MEMORY_MARK.to_string()))
        } else if watch.over(t0.get(), ops, growth) {
            Some(Dynamic::from(GROWTH_MARK.to_string()))
        } else {
            None
        }
    });
    let (sh, max_lines) = (shared.clone(), limits.max_print_lines);
    e.on_print(move |s| {
        let mut c = sh.borrow_mut();
        if c.prints.len() < max_lines {
            c.prints.push(printable(s));
        } else {
            c.prints_dropped += 1;
        }
    });
    let sh = shared.clone();
    e.on_debug(move |s, _, pos| {
        let mut c = sh.borrow_mut();
        if c.prints.len() < max_lines {
            c.prints.push(format!(
                "[line {}] {}",
                pos.line().unwrap_or(0),
                printable(s)
            ));
        } else {
            c.prints_dropped += 1;
        }
    });
    e.set_module_resolver(StdlibResolver {
        cache: RefCell::new(HashMap::new()),
    });
    let mut docs = stdlib::register(&mut e, shared);
    register_terms(&mut e, shared, &mut docs);
    register_comparer_overrides(&mut e, &mut docs);
    (e, docs)
}

/// `sort(comparer)` (and `sort_by`) and `dedup(comparer)` that report what goes wrong in the
/// comparer. Rhai's own drop its errors, taking a failed comparison for "equal" or "keep":
/// a comparer that named an unknown agent left the array unsorted, exit 0, and one that ran
/// past the wall time or the operations limit was stopped and the script went on as if
/// nothing had happened (the limits seemed not to hold). Registered on the engine, these
/// come before the package's.
fn register_comparer_overrides(e: &mut Engine, docs: &mut Vec<DocEntry>) {
    for name in ["sort", "sort_by"] {
        e.register_fn(name, sort_by_comparer);
    }
    e.register_fn("dedup", dedup_by_comparer);
    stdlib::doc(
        docs,
        "Arrays",
        "v.sort(cmp), v.sort_by(cmp), v.dedup(same)",
        "An array sorted by a comparer `|a, b| ...` (a whole number whose sign orders the pair, or true when a comes first), or its consecutive duplicates by `same` (true/false) removed; an error in the comparer is the script's error. `v.sort()` orders plain numbers, strings or booleans.",
    );
    e.register_fn("map", map_within_limits);
    e.register_fn("zip", zip_within_limits);
    // It changes the array: not to be called on a constant, as Rhai's is not.
    rhai::FuncRegistration::new("for_each")
        .with_purity(false)
        .register_into_engine(e, for_each_within_limits);
    stdlib::doc(
        docs,
        "Arrays",
        "v.map(f), v.zip(w, f), v.for_each(f)",
        "A new array of `f(x)` (or `f(x, i)`) for each element `x` at index `i`, of `f(x, y)` (or `f(x, y, i)`) for the elements of `v` and `w` side by side, or each element replaced in place where `f` assigns `this`. The array and string size limits hold as the array grows, not only once it is whole.",
    );
}

/// The size of a value as Rhai's data limits count it: array elements, map entries and string
/// bytes, nested values included.
#[derive(Debug, Clone, Copy, Default, PartialEq)]
struct DataSize {
    elements: usize,
    entries: usize,
    bytes: usize,
}

impl std::ops::Add for DataSize {
    type Output = Self;
    fn add(self, o: Self) -> Self {
        DataSize {
            elements: self.elements + o.elements,
            entries: self.entries + o.entries,
            bytes: self.bytes + o.bytes,
        }
    }
}

impl std::ops::Sub for DataSize {
    type Output = Self;
    /// Only of a part already counted in `self`.
    fn sub(self, o: Self) -> Self {
        DataSize {
            elements: self.elements - o.elements,
            entries: self.entries - o.entries,
            bytes: self.bytes - o.bytes,
        }
    }
}

impl DataSize {
    fn of(v: &Dynamic) -> Self {
        if let Ok(items) = v.as_array_ref() {
            let own = DataSize {
                elements: items.len(),
                ..Default::default()
            };
            items.iter().fold(own, |t, x| t + DataSize::of(x))
        } else if let Ok(m) = v.as_map_ref() {
            let own = DataSize {
                entries: m.len(),
                ..Default::default()
            };
            m.values().fold(own, |t, x| t + DataSize::of(x))
        } else if let Ok(s) = v.as_immutable_string_ref() {
            DataSize {
                bytes: s.len(),
                ..Default::default()
            }
        } else {
            DataSize::default()
        }
    }

    /// `v` as an element of an array: its own size and its place.
    fn element(v: &Dynamic) -> Self {
        DataSize::of(v)
            + DataSize {
                elements: 1,
                ..Default::default()
            }
    }

    /// Rhai's error for this size past one of `ctx`'s engine's data limits, if it is.
    fn check(self, ctx: &NativeCallContext) -> Result<(), Box<EvalAltResult>> {
        let e = ctx.engine();
        let over = |n: usize, max: usize| max > 0 && n > max;
        let what = if over(self.bytes, e.max_string_size()) {
            "Length of string"
        } else if over(self.elements, e.max_array_size()) {
            "Size of array/BLOB"
        } else if over(self.entries, e.max_map_size()) {
            "Size of object map"
        } else {
            return Ok(());
        };
        Err(EvalAltResult::ErrorDataTooLarge(what.into(), Position::NONE).into())
    }
}

/// Rhai's `map`, checking the array it builds against the data limits at every element: Rhai
/// checks only the whole result, so `r.map(|x| s)` over two 100,000-element arrays filled
/// memory with ten billion elements before the limit of 100,000 was looked at.
fn map_within_limits(
    ctx: NativeCallContext,
    array: &mut rhai::Array,
    f: rhai::FnPtr,
) -> Result<rhai::Array, Box<EvalAltResult>> {
    let mut out = rhai::Array::with_capacity(array.len());
    let mut size = DataSize::default();
    for (i, item) in array.iter_mut().enumerate() {
        let ex = [rhai::INT::try_from(i).unwrap_or(rhai::INT::MAX).into()];
        let v = f.call_raw_with_extra_args("map", &ctx, Some(item), [], ex, Some(0))?;
        size = size + DataSize::element(&v);
        size.check(&ctx)?;
        out.push(v);
    }
    Ok(out)
}

/// Rhai's `zip`, checked as [`map_within_limits`] is.
fn zip_within_limits(
    ctx: NativeCallContext,
    array: &mut rhai::Array,
    other: rhai::Array,
    f: rhai::FnPtr,
) -> Result<rhai::Array, Box<EvalAltResult>> {
    let mut out = rhai::Array::with_capacity(array.len().min(other.len()));
    let mut size = DataSize::default();
    for (i, (x, y)) in array.iter_mut().zip(other).enumerate() {
        let ex = [rhai::INT::try_from(i).unwrap_or(rhai::INT::MAX).into()];
        let v = f.call_raw_with_extra_args("zip", &ctx, None, [x.clone(), y], ex, None)?;
        size = size + DataSize::element(&v);
        size.check(&ctx)?;
        out.push(v);
    }
    Ok(out)
}

/// Rhai's `for_each`, checking the array against the data limits after every element it
/// replaces: `a.for_each(|| this = s)` grew `a` without limit until the call returned.
fn for_each_within_limits(
    ctx: NativeCallContext,
    array: &mut rhai::Array,
    f: rhai::FnPtr,
) -> Result<(), Box<EvalAltResult>> {
    let mut size = array
        .iter()
        .fold(DataSize::default(), |t, x| t + DataSize::element(x));
    for (i, item) in array.iter_mut().enumerate() {
        let ex = [rhai::INT::try_from(i).unwrap_or(rhai::INT::MAX).into()];
        let before = DataSize::element(item);
        let _ = f.call_raw_with_extra_args("for_each", &ctx, Some(&mut *item), [], ex, None)?;
        size = size - before + DataSize::element(item);
        size.check(&ctx)?;
    }
    Ok(())
}

fn sort_by_comparer(
    ctx: NativeCallContext,
    array: &mut rhai::Array,
    comparer: rhai::FnPtr,
) -> Result<(), Box<EvalAltResult>> {
    use std::cmp::Ordering;
    if array.len() <= 1 {
        return Ok(());
    }
    let mut failed: Option<Box<EvalAltResult>> = None;
    let mut items = std::mem::take(array);
    // `sort_by` may panic on a comparer that is no total order: an error, as Rhai's says.
    let sorted = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
        items.sort_by(|x, y| {
            if failed.is_some() {
                return Ordering::Equal;
            }
            let got = comparer
                .call_raw(&ctx, None, [x.clone(), y.clone()])
                .and_then(|v| {
                    if let Ok(n) = v.as_int() {
                        Ok(n.cmp(&0))
                    } else if let Ok(b) = v.as_bool() {
                        Ok(if b { Ordering::Less } else { Ordering::Greater })
                    } else {
                        stdlib::err(format!(
                            "sort: the comparer returned {}, not a whole number (its sign \
                             orders the pair) or true/false",
                            stdlib::a_type(&v)
                        ))
                    }
                });
            got.unwrap_or_else(|e| {
                failed = Some(e);
                Ordering::Equal
            })
        });
    }));
    *array = items;
    if let Some(e) = failed {
        return Err(e);
    }
    sorted.map_err(|_| {
        EvalAltResult::ErrorRuntime(
            "sort: the comparer is no consistent order (a < b and b < a for some pair)".into(),
            Position::NONE,
        )
        .into()
    })
}

fn dedup_by_comparer(
    ctx: NativeCallContext,
    array: &mut rhai::Array,
    comparer: rhai::FnPtr,
) -> Result<(), Box<EvalAltResult>> {
    let mut failed: Option<Box<EvalAltResult>> = None;
    array.dedup_by(|x, y| {
        if failed.is_some() {
            return false;
        }
        let got = comparer
            .call_raw(&ctx, None, [y.clone(), x.clone()])
            .and_then(|v| {
                v.as_bool().or_else(|_| {
                    stdlib::err(format!(
                        "dedup: the comparer returned {}, not true/false",
                        stdlib::a_type(&v)
                    ))
                })
            });
        got.unwrap_or_else(|e| {
            failed = Some(e);
            false
        })
    });
    failed.map_or(Ok(()), Err)
}

fn term_value(v: &Dynamic, name: &str) -> Result<Dual, Box<EvalAltResult>> {
    if let Some(d) = v.clone().try_cast::<Dual>() {
        return Ok(d);
    }
    if v.is::<Series>() {
        return stdlib::err(format!(
            "term {name:?} needs a single value, not a Series: reduce it with sum(), mean(), max(), min() or last()"
        ));
    }
    match stdlib::number(v, "term") {
        Ok(f) => Ok(Dual::constant(f)),
        Err(_) => stdlib::err(format!(
            "term {name:?}: the value is {}, not a Dual or number",
            stdlib::a_type(v)
        )),
    }
}

/// What a script printed, as terminals may show it: control characters (escape sequences)
/// written as escapes.
fn printable(s: &str) -> String {
    s.chars()
        .flat_map(|ch| {
            let v: Vec<char> = if ch.is_control() {
                ch.escape_default().collect()
            } else {
                vec![ch]
            };
            v
        })
        .collect()
}

/// Most characters of a script's `throw` value shown in its error.
const MAX_THROWN_CHARS: usize = 300;

/// Longest term name, characters.
const MAX_TERM_NAME: usize = 64;

fn add_term(
    shared: &Shared,
    pos: Position,
    name: &str,
    v: &Dynamic,
    weight: f64,
    tolerance: Option<f64>,
) -> Result<(), Box<EvalAltResult>> {
    if let Some(t) = tolerance {
        if !(t.is_finite() && t >= 0.0) {
            return stdlib::err(format!(
                "term {name:?}: tolerance {} must be finite and non-negative",
                crate::geom::num(t)
            ));
        }
    }
    let value = term_value(v, name)?;
    if !value.val.is_finite() {
        return stdlib::err(format!(
            "term {name:?} is {} (check divisions, logs and square roots)",
            value.val
        ));
    }
    if let Some(&(k, g)) = value.grad.iter().find(|(_, g)| !g.is_finite()) {
        return stdlib::err(format!(
            "term {name:?} has a non-finite gradient ({g}) w.r.t. coordinate {k}"
        ));
    }
    // Finite parts whose norm overflows (`smooth_max(1e308)`: 2e300 each) passed, `cost`
    // printed a gradient norm of inf and exited 0, and sampling failed on the NaN it made.
    if !value
        .grad
        .iter()
        .map(|(_, g)| g * g)
        .sum::<f64>()
        .is_finite()
    {
        let (k, g) = value
            .grad
            .iter()
            .copied()
            .max_by(|a, b| a.1.abs().total_cmp(&b.1.abs()))
            .unwrap_or_default();
        return stdlib::err(format!(
            "term {name:?} has a gradient too large to use (its norm overflows to infinity; \
             {g:.1e} w.r.t. coordinate {k}): a scale or smoothing factor this large makes the \
             term a cliff"
        ));
    }
    if !(weight.is_finite() && weight >= 0.0) {
        return stdlib::err(format!(
            "term {name:?}: weight {} must be finite and non-negative",
            crate::geom::num(weight)
        ));
    }
    if name.trim().is_empty() {
        return stdlib::err("term names must not be empty");
    }
    // Names reach terminals, reports and the LLM's prompt: no escape sequences, no essays, and
    // none of the sampler's own terms.
    if let Err(bad) = crate::io::name::check_name(name) {
        return stdlib::err(format!(
            "term \"{}\": a name must not contain {bad}",
            crate::io::name::shown(name)
        ));
    }
    if name.chars().count() > MAX_TERM_NAME {
        return stdlib::err(format!(
            "term {:?}...: names are at most {MAX_TERM_NAME} characters",
            name.chars().take(MAX_TERM_NAME).collect::<String>()
        ));
    }
    if name.starts_with("realism_") {
        return stdlib::err(format!(
            "term {name:?}: names starting with realism_ belong to the sampler's realism terms"
        ));
    }
    let mut c = shared.borrow_mut();
    if let Some(t) = c.terms.iter().find(|t| t.name == name) {
        return stdlib::err(format!(
            "term {name:?} is declared twice (first at line {})",
            t.line.unwrap_or(0)
        ));
    }
    c.terms.push(Term {
        name: name.to_string(),
        weight,
        value,
        line: pos.line(),
        tolerance,
    });
    Ok(())
}

/// A given parameter as the script's default says it is used: a number where the default is
/// a number (`gap=` used to fail later as "no function - (&str, Dual)", naming nothing), a
/// whole number where it is one, true or false, or a word. An integer given for a decimal
/// default becomes a float, so that `param("margin", 2.0) / 4` does not divide integers.
fn param_like(name: &str, v: &Dynamic, default: &Dynamic) -> Result<Dynamic, Box<EvalAltResult>> {
    let show = |d: &Dynamic| {
        let s = crate::io::name::shown(&d.to_string());
        if d.is_string() {
            format!("\"{s}\"")
        } else {
            s
        }
    };
    let wrong = |expected: &str| {
        stdlib::err(format!(
            "parameter \"{name}\" = {}: the script takes {expected} here (its default is {})",
            show(v),
            show(default)
        ))
    };
    if default.is_float() {
        match (v.as_float(), v.as_int()) {
            (Ok(_), _) => Ok(v.clone()),
            (_, Ok(i)) => Ok(Dynamic::from(i as f64)),
            _ => wrong("a number"),
        }
    } else if default.is_int() {
        match v.as_float() {
            _ if v.is_int() => Ok(v.clone()),
            Ok(f) if f.fract() == 0.0 && f.abs() < 9.0e15 => Ok(Dynamic::from(f as i64)),
            _ => wrong("a whole number"),
        }
    } else if default.is_bool() {
        if v.is_bool() {
            Ok(v.clone())
        } else {
            wrong("true or false")
        }
    } else if default.is_string() {
        if v.is_string() {
            Ok(v.clone())
        } else {
            wrong("a word")
        }
    } else {
        Ok(v.clone())
    }
}

fn register_terms(e: &mut Engine, shared: &Shared, docs: &mut Vec<DocEntry>) {
    const S: &str = "Terms";
    stdlib::doc(docs, S, "param(name)", "The value of `--param name=value`; an error naming the missing parameter when it was not given.");
    let sh = shared.clone();
    e.register_fn(
        "param",
        move |name: &str| -> Result<Dynamic, Box<EvalAltResult>> {
            match sh.borrow().params.get(name) {
                Some(v) => Ok(v.clone()),
                None => stdlib::err(format!(
                    "parameter {name:?} is required: pass --param {name}=VALUE"
                )),
            }
        },
    );
    stdlib::doc(
        docs,
        S,
        "param(name, default)",
        "The value of `--param name=value`, or `default` when it was not given.",
    );
    let sh = shared.clone();
    e.register_fn(
        "param",
        move |name: &str, default: Dynamic| -> Result<Dynamic, Box<EvalAltResult>> {
            match sh.borrow().params.get(name) {
                None => Ok(default),
                Some(v) => param_like(name, v, &default),
            }
        },
    );
    stdlib::doc(docs, S, "term(name, value)", "Declares a named cost term (a Dual or number, weight 1); the total cost is the weighted sum of all terms.");
    let sh = shared.clone();
    e.register_fn(
        "term",
        move |ctx: NativeCallContext, name: &str, v: Dynamic| {
            add_term(&sh, ctx.call_position(), name, &v, 1.0, None)
        },
    );
    stdlib::doc(
        docs,
        S,
        "term(name, value, weight)",
        "The same with a non-negative weight.",
    );
    let sh = shared.clone();
    e.register_fn(
        "term",
        move |ctx: NativeCallContext, name: &str, v: Dynamic, w: Dynamic| {
            add_term(
                &sh,
                ctx.call_position(),
                name,
                &v,
                stdlib::number(&w, "term weight")?,
                None,
            )
        },
    );
    stdlib::doc(
        docs,
        S,
        "term(name, value, weight, tolerance)",
        "The same with the value at or below which the term counts as met (the LLM loop accepts a sample only when every term is within its tolerance; default `--tolerance`, 0.05).",
    );
    let sh = shared.clone();
    e.register_fn(
        "term",
        move |ctx: NativeCallContext, name: &str, v: Dynamic, w: Dynamic, tol: Dynamic| {
            add_term(
                &sh,
                ctx.call_position(),
                name,
                &v,
                stdlib::number(&w, "term weight")?,
                Some(stdlib::number(&tol, "term tolerance")?),
            )
        },
    );
}

/// A scene with no map and no agents: enough to build an engine and list what it registers.
fn empty_scene() -> Rc<Scene> {
    let meta = crate::scene::SceneMeta {
        source_format: crate::scene::SourceFormat::Yaml,
        source_file: String::new(),
        scenario_id: "reference".into(),
        dt: 0.1,
        current_step: 0,
        ego: None,
        warnings: vec![],
    };
    Rc::new(Scene::new(meta, crate::scene::Map::empty(), vec![]).expect("an empty scene is valid"))
}

/// The script API as the engine registers it: natives (by section) and the stdlib modules.
pub fn reference() -> Vec<DocEntry> {
    let scene = empty_scene();
    let script = CostScript::compile(
        "",
        "reference",
        scene,
        &Params::default(),
        &Limits::default(),
    )
    .expect("the empty script compiles");
    script.docs
}

/// `///` comments and signatures of the functions of a stdlib Rhai module.
pub fn module_functions(source: &str) -> Vec<(String, String)> {
    let mut out = Vec::new();
    let mut comment: Vec<String> = Vec::new();
    for line in source.lines() {
        let t = line.trim();
        if let Some(c) = t.strip_prefix("///") {
            comment.push(c.trim().to_string());
        } else if let Some(rest) = t.strip_prefix("fn ") {
            let sig = rest.split('{').next().unwrap_or(rest).trim().to_string();
            out.push((sig, comment.join(" ")));
            comment.clear();
        } else if !t.is_empty() {
            comment.clear();
        }
    }
    out
}

/// The reference `drivescript stdlib-doc` prints and the LLM prompts include (markdown).
pub fn reference_markdown() -> String {
    reference_markdown_without(&[])
}

/// [`reference_markdown`] without the named sections (`"Frenet frame"`: the reference a model
/// gets in the paper's no-Frenet ablation); a module that uses a left-out section's functions
/// is left out too.
pub fn reference_markdown_without(sections: &[&str]) -> String {
    let mut md = String::from(
        "# drivescript cost-script reference\n\n\
Scripts are Rhai. They see the scene and one set of candidate trajectories, and declare named \
terms with `term(name, value)`; the total cost is the weighted sum of the terms, and sampling \
is guided by its gradient. Values are `Series` (one dual number per future step: element 0 is \
the step after the current one), `Dual` (one dual number) or plain numbers; arithmetic mixes \
them freely. Units are metres, seconds and radians; `d` is positive to the left. Parameters \
given with `--param name=value` are constants, as are `DT` (seconds per step) and `STEPS` \
(number of future steps). Steps where an agent is not observed are skipped by reductions.\n",
    );
    let docs: Vec<DocEntry> = reference()
        .into_iter()
        .filter(|d| !sections.contains(&d.section))
        .collect();
    let dropped: Vec<String> = reference()
        .into_iter()
        .filter(|d| sections.contains(&d.section))
        .filter_map(|d| {
            let name = d
                .signature
                .split(['(', ' ', ','])
                .next()?
                .trim_start_matches("a.");
            (!name.is_empty()).then(|| name.to_string())
        })
        .collect();
    let mut section = "";
    for d in &docs {
        if d.section != section {
            section = d.section;
            md.push_str(&format!(
                "\n## {section}\n\n| signature | meaning |\n|---|---|\n"
            ));
        }
        md.push_str(&format!(
            "| `{}` | {} |\n",
            d.signature.replace('|', "\\|"),
            d.doc.replace('|', "\\|")
        ));
    }
    for (name, src) in STDLIB_MODULES {
        if dropped
            .iter()
            .any(|f| src.contains(&format!("{f}(")) || src.contains(&format!(".{f}")))
        {
            continue;
        }
        md.push_str(&format!(
            "\n## Module `{name}` (stdlib/{name}.rhai)\n\nImport with `import \"{name}\" as m;` and call `m::function(...)`.\n\n| function | meaning |\n|---|---|\n"
        ));
        for (sig, doc) in module_functions(src) {
            md.push_str(&format!("| `{sig}` | {doc} |\n"));
        }
    }
    md
}

impl CostScript {
    /// Compiles `source` (named `name` in messages) for `scene` with `params` as constants.
    /// Parameters are also visible as `DT` (seconds per step) and `STEPS` (future steps).
    pub fn compile(
        source: &str,
        name: &str,
        scene: Rc<Scene>,
        params: &Params,
        limits: &Limits,
    ) -> Result<Self, CostError> {
        Self::compile_with(source, name, scene, params, limits, true)
    }

    /// [`CostScript::compile`], refusing names no scope defines only where `strict_variables`.
    fn compile_with(
        source: &str,
        name: &str,
        scene: Rc<Scene>,
        params: &Params,
        limits: &Limits,
        strict_variables: bool,
    ) -> Result<Self, CostError> {
        let traj = Trajectories::filled(&scene);
        let started = Rc::new(Cell::new(Instant::now()));
        let ops = Rc::new(Cell::new(0));
        let shared: Shared = Rc::new(RefCell::new(Ctx {
            clock: (started.clone(), limits.wall_time),
            scene: scene.clone(),
            traj,
            terms: Vec::new(),
            prints: Vec::new(),
            prints_dropped: 0,
            paths: HashMap::new(),
            widths: HashMap::new(),
            coords: HashMap::new(),
            may_reverse: Vec::new(),
            may_collide: Vec::new(),
            named: Vec::new(),
            params: params
                .0
                .iter()
                .map(|(k, v)| {
                    let d = match v {
                        ParamValue::Int(i) => Dynamic::from(*i),
                        ParamValue::Float(f) => Dynamic::from(*f),
                        ParamValue::Bool(b) => Dynamic::from(*b),
                        ParamValue::Str(s) => Dynamic::from(s.clone()),
                    };
                    (k.clone(), d)
                })
                .collect(),
        }));
        if source.len() > limits.max_source_bytes {
            return Err(CostError::Limit {
                script: name.into(),
                limit: format!(
                    "script size ({} bytes, max {}): a cost script is a few dozen lines",
                    source.len(),
                    limits.max_source_bytes
                ),
                line: 1,
                column: 1,
            });
        }
        no_reserved(params)?;
        let (mut engine, docs) = build_engine(&shared, limits, &started, &ops);
        engine.set_strict_variables(strict_variables);
        let mut scope = Scope::new();
        scope.push_constant("DT", scene.meta.dt);
        scope.push_constant("STEPS", scene.num_future_steps() as i64);
        for (k, v) in shared.borrow().params.iter() {
            scope.push_constant_dynamic(k.as_str(), v.clone());
        }
        started.set(Instant::now());
        ops.set(0);
        let ast = engine
            .compile_into_self_contained(&scope, source)
            .map_err(|e| {
                let pos = e.position();
                let (mut line, mut column) = (pos.line().unwrap_or(0), pos.position().unwrap_or(0));
                // Imports are resolved while compiling, without a position: find the import.
                let module = match &*e {
                    EvalAltResult::ErrorModuleNotFound(m, _) => m.split(' ').next(),
                    EvalAltResult::ErrorInModule(m, ..) => Some(m.as_str()),
                    _ => None,
                };
                if let (0, Some(m)) = (line, module) {
                    let quoted = format!("\"{m}\"");
                    if let Some((k, l)) = source
                        .lines()
                        .enumerate()
                        .find(|(_, l)| l.contains("import") && l.contains(&quoted))
                    {
                        line = k + 1;
                        column = l.find("import").map_or(1, |c| c + 1);
                    }
                }
                match *e {
                    EvalAltResult::ErrorParsing(ParseErrorType::ExprTooDeep, _) => {
                        CostError::Limit {
                            script: name.into(),
                            limit: format!("expression depth (max {})", limits.max_expr_depth),
                            line,
                            column,
                        }
                    }
                    EvalAltResult::ErrorParsing(
                        ParseErrorType::LiteralTooLarge(ref what, max),
                        _,
                    ) => CostError::Limit {
                        script: name.into(),
                        limit: format!("{what} (max {max})"),
                        line,
                        column,
                    },
                    EvalAltResult::ErrorParsing(ref kind, _) => CostError::Syntax {
                        script: name.into(),
                        line,
                        column,
                        // The variant's own text: the whole error's repeats "Syntax error".
                        message: strip_position(&kind.to_string()),
                    },
                    EvalAltResult::ErrorModuleNotFound(..) | EvalAltResult::ErrorInModule(..) => {
                        CostError::Runtime {
                            script: name.into(),
                            line,
                            column,
                            message: strip_position(&e.to_string()),
                        }
                    }
                    ref other => CostError::Syntax {
                        script: name.into(),
                        line,
                        column,
                        message: strip_position(&other.to_string()),
                    },
                }
            })?;
        Ok(Self {
            name: name.to_string(),
            engine,
            ast,
            scope,
            shared,
            started,
            ops,
            limits: limits.clone(),
            docs,
            used: Cell::new(Usage::default()),
        })
    }

    /// Evaluations of this script so far, and the time they took.
    pub fn usage(&self) -> Usage {
        self.used.get()
    }

    /// Compiles `source` without a scene: what fails here (syntax, imports, size limits) fails
    /// on every scene, so a command with many scenes says it once, before any work. A name no
    /// scope defines is not refused here: parameters are constants of the scope (`cutter` for
    /// `--param cutter=1`), given with each scene, and this check has none, so every script
    /// reading one was refused as "Undefined variable" (`simulate --script --param`, Python's
    /// `CostScript.from_source(params=...)`). Such a name is refused on the first scene.
    pub fn check_syntax(source: &str, name: &str, limits: &Limits) -> Result<(), CostError> {
        let meta = crate::scene::SceneMeta {
            source_format: crate::scene::SourceFormat::Yaml,
            source_file: String::new(),
            scenario_id: "syntax-check".into(),
            dt: 0.1,
            current_step: 0,
            ego: None,
            warnings: Vec::new(),
        };
        let scene = Scene::new(meta, crate::scene::Map::empty(), Vec::new())
            .expect("an empty scene is consistent");
        Self::compile_with(
            source,
            name,
            Rc::new(scene),
            &Params::default(),
            limits,
            false,
        )
        .map(|_| ())
    }

    /// The script's name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// The documentation of every function the engine registers.
    pub fn docs(&self) -> &[DocEntry] {
        &self.docs
    }

    /// The engine, for tools that inspect what it registers.
    pub fn engine(&self) -> &Engine {
        &self.engine
    }

    /// A dry run before any sampling, on the recorded future with gaps filled: the script runs,
    /// declares at least one term, and every term is finite and depends on some trajectory.
    pub fn validate(&self) -> Result<CostReport, CostError> {
        let traj = Trajectories::filled(&self.shared.borrow().scene);
        let report = self.evaluate(&traj)?;
        if report.terms.is_empty() {
            return Err(CostError::NoTerms {
                script: self.name.clone(),
            });
        }
        for t in &report.terms {
            if t.grad.is_empty() {
                return Err(CostError::Term {
                    script: self.name.clone(),
                    term: t.name.clone(),
                    line: t.line,
                    message: format!(
                        "it is the constant {} and does not depend on any trajectory (history values and parameters alone cannot guide sampling)",
                        t.value
                    ),
                });
            }
        }
        Ok(report)
    }

    /// The terms that can never steer sampling: a zero gradient on the recorded future (gaps
    /// filled) and on every perturbed future of [`super::probe::PROBES`], whatever their value. A guard
    /// that is 0 on the log but wakes when cars collide, leave the road or speed up is not
    /// one of them. Where the script fails on a probe (a lane lookup far off the map, say), or
    /// declares other terms there, nothing is said: only what every probe shows is reported.
    /// The probes share one wall clock, [`Limits::wall_time`] for all of them: each with its
    /// own, a script just inside the limit ran fifteen times as long (`cost` took 52 s on a
    /// five-line script); past it, nothing is said either.
    /// Run after [`CostScript::validate`] (whose errors it does not repeat).
    pub fn dead_terms(&self) -> Vec<DeadTerm> {
        let futures = {
            let c = self.shared.borrow();
            let mut f = vec![Trajectories::filled(&c.scene)];
            f.extend(super::probe::probe_futures(&c.scene));
            f
        };
        // Each term with a zero weighted gradient on every probe so far, a value other than 0
        // it took on one, and its weight where its unweighted gradient moved on one.
        type Still = (String, usize, Option<f64>, Option<f64>);
        let mut dead: Option<Vec<Still>> = None;
        let since = Instant::now();
        for traj in &futures {
            let Ok(report) = self.evaluate_since(traj, Some(since)) else {
                return Vec::new();
            };
            let here: Vec<Still> = report
                .terms
                .iter()
                // The sampler steers in single precision: a product that rounds to 0 there
                // (a weight of 1e-320) moves nothing, as a weight of 0 does.
                .filter(|t| t.grad.iter().all(|(_, g)| (t.weight * g) as f32 == 0.0))
                .map(|t| {
                    let moved = t.grad.iter().any(|(_, g)| *g != 0.0);
                    (
                        t.name.clone(),
                        t.line,
                        (t.value != 0.0).then_some(t.value),
                        moved.then_some(t.weight),
                    )
                })
                .collect();
            dead = Some(match dead {
                None => here,
                Some(d) => d
                    .into_iter()
                    .filter_map(|(name, line, value, weight)| {
                        let now = here.iter().find(|h| h.0 == name && h.1 == line)?;
                        Some((name, line, value.or(now.2), weight.or(now.3)))
                    })
                    .collect(),
            });
            if dead.as_ref().is_some_and(Vec::is_empty) {
                break;
            }
        }
        dead.unwrap_or_default()
            .into_iter()
            .map(|(term, line, value, weighted_out)| DeadTerm {
                script: self.name.clone(),
                term,
                line,
                value,
                weighted_out,
            })
            .collect()
    }

    /// Evaluates every term and its gradient on candidate trajectories.
    pub fn evaluate(&self, traj: &Trajectories) -> Result<CostReport, CostError> {
        self.evaluate_since(traj, None)
    }

    /// [`CostScript::evaluate`] with the wall clock started at `since` (now when `None`).
    fn evaluate_since(
        &self,
        traj: &Trajectories,
        since: Option<Instant>,
    ) -> Result<CostReport, CostError> {
        {
            let mut c = self.shared.borrow_mut();
            if traj.layout.steps == 0 {
                return Err(CostError::NoFuture {
                    script: self.name.clone(),
                    scene: c.scene.meta.scenario_id.clone(),
                    current: c.scene.meta.current_step,
                });
            }
            let expect = VarLayout::of(&c.scene);
            if traj.layout != expect || traj.xyh.len() != expect.agents * expect.steps {
                return Err(CostError::Shape {
                    script: self.name.clone(),
                    message: format!(
                        "{} agents x {} steps given, the scene has {} x {}",
                        traj.layout.agents, traj.layout.steps, expect.agents, expect.steps
                    ),
                });
            }
            // In place: the buffers of the last call are reused, not allocated again.
            c.traj.layout = traj.layout;
            c.traj.xyh.clone_from(&traj.xyh);
            c.traj.valid.clone_from(&traj.valid);
            c.terms.clear();
            c.prints.clear();
            c.prints_dropped = 0;
            c.coords.clear();
            c.may_reverse.clear();
            c.may_collide.clear();
            c.named.clear();
        }
        let t0 = Instant::now();
        self.started.set(since.unwrap_or(t0));
        self.ops.set(0);
        let mut scope = self.scope.clone();
        let run = self.engine.run_ast_with_scope(&mut scope, &self.ast);
        self.used.set(self.used.get().plus(Usage {
            evaluations: 1,
            time: t0.elapsed(),
        }));
        run.map_err(|e| self.map_error(&e))?;
        let c = self.shared.borrow();
        let terms: Vec<TermReport> = c
            .terms
            .iter()
            .map(|t| TermReport {
                name: t.name.clone(),
                weight: t.weight,
                value: t.value.val,
                line: t.line.unwrap_or(0),
                tolerance: t.tolerance,
                grad: (*t.value.grad).clone(),
            })
            .collect();
        let mut prints = c.prints.clone();
        // The lines past the cap were dropped without a word: 100,000 prints in a loop
        // showed 200 lines, as if the loop had run 200 times.
        if c.prints_dropped > 0 {
            prints.push(format!(
                "... and {} more print lines, not kept (at most {} are)",
                c.prints_dropped, self.limits.max_print_lines
            ));
        }
        let mut report = CostReport::new(terms, traj.layout, prints, t0.elapsed());
        // Finite weights times finite values can still overflow; a total of inf would reach
        // the sampler as a gradient naming neither term nor script. The per-term search runs
        // only when the sums say something overflowed.
        if !(report.total.is_finite() && report.gradient.iter().all(|g| g.is_finite())) {
            let culprit = report.terms.iter().find(|t| {
                !(t.weight * t.value).is_finite()
                    || t.grad.iter().any(|(_, g)| !(t.weight * g).is_finite())
            });
            return Err(match culprit {
                Some(t) => CostError::Term {
                    script: self.name.clone(),
                    term: t.name.clone(),
                    line: t.line,
                    message: format!(
                        "weight {:e} × value {:e} (or its gradient) overflows to infinity; use a smaller weight",
                        t.weight, t.value
                    ),
                },
                None => CostError::Term {
                    script: self.name.clone(),
                    term: report
                        .terms
                        .iter()
                        .max_by(|a, b| (a.weight * a.value).total_cmp(&(b.weight * b.value)))
                        .map(|t| t.name.clone())
                        .unwrap_or_default(),
                    line: 0,
                    message: format!(
                        "the weighted total overflows to {}; use smaller weights",
                        report.total
                    ),
                },
            });
        }
        report.may_reverse = c.may_reverse.clone();
        report.may_collide = c.may_collide.clone();
        report.named = c.named.clone();
        Ok(report)
    }

    /// Evaluates a batch of candidates (K samples of one scene).
    pub fn evaluate_batch(&self, trajs: &[Trajectories]) -> Result<Vec<CostReport>, CostError> {
        trajs.iter().map(|t| self.evaluate(t)).collect()
    }

    /// For a call no function takes: the given parameters whose type is among its argument
    /// types (`gap=abc` where a number belongs), which most often are why.
    fn given_in(&self, sig: &str) -> String {
        let args = match (sig.find('('), sig.rfind(')')) {
            (Some(a), Some(b)) if a < b => &sig[a + 1..b],
            _ => return String::new(),
        };
        let ctx = self.shared.borrow();
        let found: Vec<String> = ctx
            .params
            .iter()
            .filter_map(|(k, v)| {
                let (what, in_sig) = if v.is_string() {
                    ("a string", "String")
                } else if v.is_float() {
                    ("an f64", "f64")
                } else if v.is_bool() {
                    ("a bool", "bool")
                } else {
                    return None;
                };
                args.contains(in_sig).then(|| {
                    format!(
                        "{what} is --param {k}={}",
                        crate::io::name::shown(&v.to_string())
                    )
                })
            })
            .collect();
        if found.is_empty() {
            String::new()
        } else {
            format!(
                ": {}, which the script uses where it takes another type",
                found.join("; ")
            )
        }
    }

    fn map_error(&self, e: &EvalAltResult) -> CostError {
        let script = self.name.clone();
        let pos = e.position();
        let (line, column) = (pos.line().unwrap_or(0), pos.position().unwrap_or(0));
        let limit = |limit: String| CostError::Limit {
            script: script.clone(),
            limit,
            line,
            column,
        };
        let l = &self.limits;
        match e {
            EvalAltResult::ErrorTooManyOperations(_) => limit(format!("operations (max {})", l.max_operations)),
            EvalAltResult::ErrorStackOverflow(_) => limit(format!("call depth (max {})", l.max_call_levels)),
            EvalAltResult::ErrorTooManyVariables(_) => limit(format!("variables (max {})", l.max_variables)),
            EvalAltResult::ErrorTooManyModules(_) => limit(format!("modules (max {})", l.max_modules)),
            EvalAltResult::ErrorDataTooLarge(what, _) => {
                let max = if what.contains("string") || what.contains("String") {
                    format!("max {} characters", l.max_string_size)
                } else if what.contains("rray") {
                    format!("max {} elements", l.max_array_size)
                } else if what.contains("ap") {
                    format!("max {} entries", l.max_map_size)
                } else {
                    "limit".to_string()
                };
                limit(format!("{what} ({max})"))
            }
            EvalAltResult::ErrorTerminated(tok, _) if tok.to_string() == OPERATIONS_MARK => {
                limit(format!("operations (max {})", l.max_operations))
            }
            EvalAltResult::ErrorTerminated(tok, _) if tok.to_string() == WALL_TIME_MARK => {
                limit(format!("wall time (max {:.1} s)", l.wall_time.as_secs_f64()))
            }
            EvalAltResult::ErrorTerminated(tok, _) if tok.to_string() == GROWTH_MARK => limit(
                format!(
                    "memory (the process grew by over {} MB in this evaluation; arrays or maps \
                     of copies, e.g. `a[i] = s` of a large `s`, hold more than the size limits \
                     count)",
                    l.max_memory_growth >> 20
                ),
            ),
            EvalAltResult::ErrorTerminated(tok, _) if tok.to_string() == MEMORY_MARK => limit(
                format!(
                    "memory (max {} MB of series held at once; keep fewer series alive, e.g. \
                     sum them as you go instead of collecting them)",
                    l.max_series_bytes >> 20
                ),
            ),
            EvalAltResult::ErrorInFunctionCall(f, _, inner, _) | EvalAltResult::ErrorInModule(f, inner, _) => {
                // Report the innermost cause at the outermost position (in the user's script).
                let inner_err = self.map_error(inner);
                match inner_err {
                    CostError::Limit { limit, .. } => CostError::Limit { script, limit, line, column },
                    // Rhai names a closure by a hash ("anon$89dfda3c82566aec"), which names
                    // nothing in the script.
                    other if f.starts_with("anon$") => CostError::Runtime {
                        script,
                        line,
                        column,
                        message: format!("in a closure (|...| ...): {}", error_message(&other)),
                    },
                    other => CostError::Runtime {
                        script,
                        line,
                        column,
                        message: format!("in {f}: {}", error_message(&other)),
                    },
                }
            }
            // The stdlib's own errors have no position; one with a position is the script's
            // `throw`, whose value can be 10,000 characters: it reaches terminals and prompts.
            EvalAltResult::ErrorRuntime(v, pos) if !pos.is_none() => {
                let raw = v.to_string();
                // On one line, as every error is: a line break in the thrown text printed a
                // line of the script's choosing under drivescript's own ("Verdict: met").
                let text = printable(&raw);
                let n = text.chars().count();
                // `throw;` and `throw ""` printed "s.rhai:1:1: " and nothing after it.
                let message = if raw.trim().is_empty() {
                    if v.is_unit() { "the script threw () without a message".to_string() } else { "the script threw a blank message".to_string() }
                } else if n > MAX_THROWN_CHARS {
                    format!(
                        "{}... ({} more characters)",
                        text.chars().take(MAX_THROWN_CHARS).collect::<String>(),
                        n - MAX_THROWN_CHARS
                    )
                } else {
                    text
                };
                CostError::Runtime { script, line, column, message }
            }
            EvalAltResult::ErrorRuntime(v, _) => CostError::Runtime { script, line, column, message: v.to_string() },
            // Rhai's `sort()` says what it cannot order as a function not found, with the Rust
            // type path: "no function elements of drivescript::cost::dual::Dual cannot be sorted".
            EvalAltResult::ErrorFunctionNotFound(sig, _) if sig.starts_with("elements of ") => CostError::Runtime {
                script,
                line,
                column,
                message: format!(
                    "sort: {}: sort() orders plain numbers, strings or booleans of one type; a Dual or Series has no order of its own (sort value(x), or give sort a comparer)",
                    sig.replace("drivescript::cost::dual::", "").replace("drivescript::cost::series::", "")
                ),
            },
            // A closure that captures the array it is mapped over (`a.map(|x| a.len())`) said
            // "Data race detected on argument #1 of function 'map'": Rhai's words for a variable
            // lent twice at once, with no way out.
            EvalAltResult::ErrorDataRace(what, _) => CostError::Runtime {
                script,
                line,
                column,
                message: format!(
                    "{} is also held by a closure (|...| ...) that runs while it is in use; give \
                     the closure a copy instead (`let c = a;` before it, and `c` inside)",
                    if what.is_empty() { "a variable" } else { what.as_str() }
                ),
            },
            // "Indexer unavailable: Series [i64]" named Rhai's machinery and Rust's integer
            // type, not what to write instead.
            EvalAltResult::ErrorIndexingType(t, _) => {
                let what = t.split(" [").next().unwrap_or(t).trim();
                let hint = match what {
                    "Series" => ": use s.at(i) for element i (negative counts from the end), or s.at_time(t)",
                    "Dual" => ": a Dual is one number; value(x) gives it as a float",
                    _ => "",
                };
                CostError::Runtime {
                    script,
                    line,
                    column,
                    message: format!("a value of type {what} cannot be indexed with [ ]{hint}"),
                }
            }
            EvalAltResult::ErrorFunctionNotFound(sig, _) => CostError::Runtime {
                script,
                line,
                column,
                message: format!("no function {}{} (see `drivescript stdlib-doc` for what exists and its argument types)", script_types(sig), self.given_in(sig)),
            },
            // Rhai's own: "No writable property 'x' - a setter is not registered for type
            // 'Agent' to handle 'i64'", in Rust's type names.
            EvalAltResult::ErrorDotExpr(m, _) if m.starts_with("No writable property '") => {
                let prop = m.split('\'').nth(1).unwrap_or("?");
                let of = m.split('\'').nth(3).unwrap_or("this value");
                CostError::Runtime {
                    script,
                    line,
                    column,
                    message: format!(
                        ".{prop} cannot be assigned: a value of type {} has read-only properties (keep \
                         what you compute in a variable of your own)",
                        script_types(&format!("({of})")).trim_matches(['(', ')'])
                    ),
                }
            }
            other => CostError::Runtime { script, line, column, message: short_numbers(&strip_position(&other.to_string())) },
        }
    }
}

fn error_message(e: &CostError) -> String {
    match e {
        CostError::Runtime { message, .. }
        | CostError::Syntax { message, .. }
        | CostError::Term { message, .. } => message.clone(),
        other => other.to_string(),
    }
}

/// A function signature of Rhai's (`len (range=)`, `- (&str | ImmutableString | String, i64)`)
/// with its arguments' types named as a script knows them: `string`, not the Rust types Rhai
/// lists for one, and `inclusive range` for the `range=` of `a..=b`.
fn script_types(sig: &str) -> String {
    let (Some(a), Some(b)) = (sig.find('('), sig.rfind(')')) else {
        return sig.to_string();
    };
    if a >= b {
        return sig.to_string();
    }
    let args = sig[a + 1..b]
        .replace("&str | ImmutableString | String", "string")
        .split(", ")
        .map(|t| match t.trim() {
            "range=" => "inclusive range",
            "range" => "range",
            _ => t,
        })
        .collect::<Vec<_>>()
        .join(", ");
    format!("{}({args}){}", &sig[..a], &sig[b + 1..])
}

/// `message` with every number of more than 20 digits (Rhai prints the float in
/// `to_int(1e300)`'s overflow to its last of 301 digits) in exponent form.
fn short_numbers(message: &str) -> String {
    let bytes = message.as_bytes();
    let mut out = String::with_capacity(message.len());
    let mut i = 0;
    while i < bytes.len() {
        let number = |j: usize| bytes[j].is_ascii_digit() || bytes[j] == b'.';
        if bytes[i].is_ascii_digit() && (i == 0 || !number(i - 1)) {
            let mut j = i;
            while j < bytes.len() && number(j) {
                j += 1;
            }
            let run = &message[i..j];
            let digits = run.bytes().filter(u8::is_ascii_digit).count();
            match run.parse::<f64>() {
                Ok(v) if digits > 20 => out.push_str(&format!("{v:e}")),
                _ => out.push_str(run),
            }
            i = j;
        } else {
            let c = message[i..].chars().next().expect("within the message");
            out.push(c);
            i += c.len_utf8();
        }
    }
    out
}

/// Rhai appends " (line N, position M)" to its messages; the location is reported separately.
fn strip_position(s: &str) -> String {
    match s.rfind(" (line ") {
        Some(i) if s.ends_with(')') => s[..i].to_string(),
        _ => s.to_string(),
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn an_error_names_as_much_of_its_place_as_is_known() {
        let limit = |line, column| {
            super::CostError::Limit {
                script: "m.rhai".into(),
                limit: "wall time (max 5.0 s)".into(),
                line,
                column,
            }
            .to_string()
        };
        assert_eq!(
            limit(5, 26),
            "m.rhai:5:26: limit exceeded: wall time (max 5.0 s)"
        );
        assert_eq!(
            limit(5, 0),
            "m.rhai:5: limit exceeded: wall time (max 5.0 s)"
        );
        // It said "m.rhai:0:0:", a place that is in no file.
        assert_eq!(limit(0, 0), "m.rhai: limit exceeded: wall time (max 5.0 s)");
        let term = super::CostError::Term {
            script: "s.rhai".into(),
            term: "a".into(),
            line: 0,
            message: "the weighted total overflows to inf; use smaller weights".into(),
        };
        assert!(
            term.to_string().starts_with("s.rhai: term \"a\": "),
            "{term}"
        );
    }

    #[test]
    fn parameters_are_found_as_calls_and_as_constants_not_inside_words() {
        let src = "let m = param(\"margin\", 0.5);\nlet w = weight * 2.0; // reweighted\n";
        assert_eq!(super::script_params(src), vec!["margin".to_string()]);
        assert!(super::uses_param(src, "margin") && super::uses_param(src, "weight"));
        assert!(!super::uses_param(src, "m2") && !super::uses_param(src, "eight"));
    }

    #[test]
    fn a_parameter_named_only_in_a_comment_or_as_a_keyword_function_or_property_is_not_read() {
        let src =
            "// keep the margin wide\n/* the gap /* nested */ gap */\nlet a = agent(cutter);\n\
                   term(\"x\", a.speed * w2 + f(`${tol} m`) + 1e5 + '\\'' );\n";
        for unread in [
            "margin", "gap", "nested", "let", "term", "agent", "speed", "e5", "x0",
        ] {
            assert!(!super::uses_param(src, unread), "{unread}");
        }
        for read in ["cutter", "w2", "tol", "x"] {
            assert!(super::uses_param(src, read), "{read}");
        }
        assert!(super::uses_param("let m = param(\"let\", 1.0);", "let"));
    }

    use super::*;

    /// Names a documentation signature covers: functions, `get$` properties and operators.
    fn documented_names(sig: &str) -> Vec<String> {
        let mut out = Vec::new();
        for item in sig.split(", ").flat_map(|p| p.split(" or ")) {
            let item = item.split(" -> ").next().unwrap_or(item).trim();
            if let Some(i) = item.find('(') {
                let head = &item[..i];
                if !head.is_empty() {
                    out.push(head.rsplit('.').next().unwrap_or(head).to_string());
                }
            } else if let Some((_, prop)) = item.split_once('.') {
                out.push(format!("get${}", prop.trim()));
            } else if let Some(op) = item.split_whitespace().nth(1) {
                out.push(op.to_string());
            } else if let Some(op) = item.strip_suffix('x') {
                out.push(op.to_string());
            }
        }
        out
    }

    #[test]
    fn every_registered_function_is_documented_and_vice_versa() {
        let docs = reference();
        let documented: std::collections::BTreeSet<String> = docs
            .iter()
            .flat_map(|d| documented_names(d.signature))
            .collect();
        let scene = empty_scene();
        let script =
            CostScript::compile("", "t", scene, &Params::default(), &Limits::default()).unwrap();
        let registered: std::collections::BTreeSet<String> = script
            .engine()
            .gen_fn_signatures(false)
            .iter()
            .map(|s| s.split('(').next().unwrap().to_string())
            // Display hooks for print, not part of the API.
            .filter(|n| n != "to_string" && n != "to_debug")
            .collect();
        let missing: Vec<_> = registered.difference(&documented).collect();
        let stale: Vec<_> = documented.difference(&registered).collect();
        assert!(
            missing.is_empty(),
            "registered but undocumented: {missing:?}"
        );
        assert!(stale.is_empty(), "documented but not registered: {stale:?}");
    }

    /// The script test highway: a straight 500 m road along +x in two segments (lanes
    /// 100-102 then 200-202).
    fn highway() -> crate::scene::Scene {
        let p =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        crate::io::load_scene(&p, 0, &crate::io::LoadOptions::default()).unwrap()
    }

    /// The error that compiling and evaluating `src` on the recorded future gives.
    fn evaluation_error(src: &str, scene: Rc<crate::scene::Scene>) -> CostError {
        let traj = crate::cost::Trajectories::recorded(&scene);
        CostScript::compile(src, "t", scene, &Params::default(), &Limits::default())
            .and_then(|s| s.evaluate(&traj))
            .unwrap_err()
    }

    /// `src`'s report on the recorded future of `scene`.
    fn evaluate_recorded(src: &str, scene: crate::scene::Scene) -> crate::cost::CostReport {
        let scene = Rc::new(scene);
        CostScript::compile(
            src,
            "t",
            scene.clone(),
            &Params::default(),
            &Limits::default(),
        )
        .unwrap()
        .evaluate(&crate::cost::Trajectories::recorded(&scene))
        .unwrap()
    }

    /// The error of compiling and evaluating `src` on the highway with `--param` `args`.
    fn error_with(src: &str, args: &[&str]) -> String {
        let scene = Rc::new(highway());
        let traj = crate::cost::Trajectories::recorded(&scene);
        let params = Params::parse(args).unwrap();
        CostScript::compile(src, "t", scene, &params, &Limits::default())
            .and_then(|s| s.evaluate(&traj))
            .unwrap_err()
            .to_string()
    }

    #[test]
    fn a_parameter_the_script_cannot_use_is_named_with_its_value_and_what_is_expected() {
        let cut_in = "let a = agent(param(\"cutter\")); let g = param(\"gap\", 5.0); \
                      term(\"x\", relu(g - a.x.last()));";
        for (args, want) in [
            // Was "no function agent (f64)".
            (
                &["cutter=1.5"][..],
                "agent(1.5): an agent id is a whole number, not a decimal number, from --param cutter=1.5",
            ),
            (
                &["cutter=left"][..],
                "agent(left): an agent id is a whole number, not a word, from --param cutter=left",
            ),
            (
                &["cutter=99"][..],
                "unknown agent id 99 (--param cutter=99); the scene has agents",
            ),
            // Was "no function - (&str | ImmutableString | String, Dual)".
            (
                &["cutter=1", "gap=abc"][..],
                "parameter \"gap\" = \"abc\": the script takes a number here (its default is 5.0)",
            ),
        ] {
            let e = error_with(cut_in, args);
            assert!(e.contains(want), "{args:?}: {e}");
        }
        // Without a default to go by, the call no function takes names the parameter.
        let e = error_with(
            "term(\"x\", relu(param(\"limit\") - agent(1).speed.max()));",
            &["limit=fast"],
        );
        assert!(
            e.contains("no function - (") && e.contains("a string is --param limit=fast"),
            "{e}"
        );
        // An integer for a decimal default is a float: 3 / 2 is 1.5, not 1.
        let r = {
            let scene = Rc::new(highway());
            CostScript::compile(
                "term(\"x\", param(\"m\", 2.0) / 2 + 0.0 * agent(1).x.last());",
                "t",
                scene.clone(),
                &Params::parse(&["m=3"]).unwrap(),
                &Limits::default(),
            )
            .unwrap()
            .evaluate(&crate::cost::Trajectories::recorded(&scene))
            .unwrap()
        };
        assert_eq!(r.total, 1.5);
        let e = error_with(
            "let n = param(\"n\", 3); term(\"x\", n * agent(1).x.last());",
            &["n=2.5"],
        );
        assert!(
            e.contains(
                "parameter \"n\" = 2.5: the script takes a whole number here (its default is 3)"
            ),
            "{e}"
        );
    }

    #[test]
    fn a_closed_loop_round_is_judged_on_the_original_horizon_and_moves_only_what_is_left() {
        use crate::cost::{Coord, Trajectories};
        let scene = Rc::new(highway());
        let src = "let a = agent(1); term(\"first\", a.x.first()); term(\"last\", a.x.last());";
        let script = CostScript::compile(
            src,
            "t",
            scene.clone(),
            &Params::default(),
            &Limits::default(),
        )
        .unwrap();
        let executed = Trajectories::recorded(&scene);
        let n = executed.layout.steps;
        let ai = scene.agents.iter().position(|a| a.id == 1).unwrap();
        // A round's sample has the model's whole horizon, past the original one.
        let mut rest = executed.clone();
        for s in &mut rest.xyh {
            s[0] += 100.0;
        }
        let done = 30;
        let whole = executed.spliced(done, &rest);
        assert_eq!(whole.state(ai, done - 1), executed.state(ai, done - 1));
        assert_eq!(whole.state(ai, done), rest.state(ai, 0));
        let r = script.evaluate(&whole).unwrap().shifted(done, rest.layout);
        assert_eq!(r.layout, rest.layout);
        assert_eq!(r.gradient.len(), rest.layout.len());
        // The first step was executed: it counts, and nothing can move it.
        let first = r.term("first").unwrap();
        assert_eq!(first.value, executed.state(ai, 0).0[0]);
        assert!(first.grad.is_empty(), "{:?}", first.grad);
        // The original horizon ends at the round's step n - 1 - done, not at its last.
        let last = r.term("last").unwrap();
        assert_eq!(last.value, rest.state(ai, n - 1 - done).0[0]);
        assert_eq!(
            last.grad,
            vec![(rest.layout.var(ai, n - 1 - done, Coord::X), 1.0)]
        );
        assert_eq!(r.total, first.value + last.value);
    }

    #[test]
    fn term_names_and_prints_cannot_carry_escape_sequences() {
        let scene = Rc::new(highway());
        for (name, want) in [
            ("\\x1b[2Jx", "the control character U+001B"),
            ("a\\nerror: b", "the control character U+000A"),
            ("realism_speed", "belong to the sampler"),
            (&"n".repeat(65), "at most 64 characters"),
            ("speed\u{202E}gnol", "the invisible character U+202E"),
            ("go\u{200B}al", "the invisible character U+200B"),
        ] {
            let src = format!("term(\"{name}\", agent(1).x.last());");
            let e = evaluation_error(&src, scene.clone()).to_string();
            assert!(e.contains(want) && !e.contains('\u{1b}'), "{name}: {e}");
        }
        let r = evaluate_recorded(
            "print(\"a\u{1b}[31mred\"); debug(\"b\u{7}\"); term(\"x\", agent(1).x.last());",
            highway(),
        );
        assert_eq!(r.prints[0], "a\\u{1b}[31mred");
        assert!(r.prints[1].ends_with("\\u{7}\""), "{:?}", r.prints);
        assert!(r.prints.iter().all(|p| !p.chars().any(char::is_control)));
    }

    #[test]
    fn prints_past_the_cap_are_counted_not_dropped_without_a_word() {
        // 1,000 prints showed 200 lines, as if the loop had run 200 times.
        let r = evaluate_recorded(
            "for i in 0..1000 { print(i); }\nterm(\"x\", agent(1).x.last());",
            highway(),
        );
        let max = Limits::default().max_print_lines;
        assert_eq!(r.prints.len(), max + 1);
        assert_eq!(r.prints[max - 1], (max - 1).to_string());
        assert_eq!(
            r.prints[max],
            format!(
                "... and {} more print lines, not kept (at most {max} are)",
                1000 - max
            )
        );
        // A few are all kept, with no count after them.
        let r = evaluate_recorded("print(1);\nterm(\"x\", agent(1).x.last());", highway());
        assert_eq!(r.prints, vec!["1".to_string()]);
    }

    #[test]
    fn weights_that_overflow_name_their_term() {
        let e = evaluation_error(
            "term(\"small\", agent(1).x.last());\nterm(\"huge\", agent(1).x.last(), 1.0e308);",
            Rc::new(highway()),
        )
        .to_string();
        assert!(e.contains("\"huge\"") && e.contains("overflows"), "{e}");
        let e = evaluation_error(
            "term(\"a\", agent(1).x.last(), 5.0e305);\nterm(\"b\", agent(1).x.last(), 5.0e305);",
            Rc::new(highway()),
        )
        .to_string();
        assert!(e.contains("weighted total overflows"), "{e}");
        // A denormal is said in a few characters, not 300 digits.
        let e = evaluation_error(
            "term(\"a\", agent(1).x.last(), -5e-324);",
            Rc::new(highway()),
        )
        .to_string();
        assert!(e.contains("weight -5e-324 must be") && e.len() < 200, "{e}");
        let e = evaluation_error(
            "term(\"a\", agent(1).x.last(), 1.0, -5e-324);",
            Rc::new(highway()),
        )
        .to_string();
        assert!(
            e.contains("tolerance -5e-324 must be") && e.len() < 200,
            "{e}"
        );
    }

    #[test]
    fn a_literal_beyond_the_largest_float_is_named_as_written() {
        // Rhai read it as infinity: "weight inf must be finite and non-negative".
        let e = evaluation_error(
            "let w = 1;\nterm(\"a\", agent(1).x.last(), 1e400);",
            Rc::new(highway()),
        )
        .to_string();
        assert!(
            e.contains("t:2:30: syntax error: the number 1e400 is beyond the largest number"),
            "{e}"
        );
        assert!(!e.contains("inf"), "{e}");
    }

    #[test]
    fn a_long_thrown_message_is_cut_and_says_how_much_is_left() {
        let e = evaluation_error(
            "let s = \"x\"; s.pad(9000, 'y'); throw s;",
            Rc::new(highway()),
        )
        .to_string();
        assert!(
            e.contains("yyy... (8700 more characters)") && e.len() < 600,
            "{e}"
        );
        let e = evaluation_error("throw \"short and clear\";", Rc::new(highway())).to_string();
        assert!(
            e.contains("short and clear") && !e.contains("more characters"),
            "{e}"
        );
    }

    #[test]
    fn terms_carry_the_tolerance_the_script_gives() {
        let r = evaluate_recorded(
            "let a = agent(1);
             term(\"plain\", a.x.last());
             term(\"loose\", a.x.last(), 2.0, 0.25);",
            highway(),
        );
        let t = |n: &str| r.term(n).unwrap();
        assert_eq!(
            (t("plain").tolerance, t("loose").tolerance),
            (None, Some(0.25))
        );
        assert_eq!(t("loose").weight, 2.0);
        let e = evaluation_error(
            "term(\"bad\", agent(1).x.last(), 1.0, -1.0);",
            Rc::new(highway()),
        )
        .to_string();
        assert!(
            e.contains("tolerance -1 must be finite and non-negative"),
            "{e}"
        );
    }

    #[test]
    fn small_words_have_known_answers() {
        // Agent 1 drives along +x at 20 m/s in lane 101 (3.6 m wide) for STEPS steps.
        let r = evaluate_recorded(
            "let a = agent(1);
             let x = a.x - a.current_x;
             term(\"sign\", sign(a.vx).sum() + sign(-2.5) + sign(0.0));
             term(\"ever_below\", x.ever_below(10.0));
             term(\"always_below\", x.always_below(10.0) - (x.max() - 10.0));
             term(\"ever_above\", x.ever_above(1000.0) - (1000.0 - x.max()));
             term(\"always_above\", x.always_above(0.0) + x.always_above(5.0) - (5.0 - x.min()));
             term(\"decides\", x.always_below(10.0));
             term(\"words\", (if a.present && a.has_future { 1.0 } else { 0.0 }) + 0.0 * a.x.last());
             term(\"width\", lane_width(a.lane, a.current_x, a.current_y) + 0.0 * a.x.last());",
            highway(),
        );
        let v = |n: &str| r.term(n).unwrap().value;
        assert_eq!(v("sign"), r.layout.steps as f64 - 1.0);
        for n in ["ever_below", "always_below", "ever_above", "always_above"] {
            assert!(v(n).abs() < 1e-9, "{n}: {}", v(n));
        }
        assert_eq!((v("words"), v("width")), (1.0, 3.6));
        // The gradient of "at every step" moves the step that decides: the last.
        let g = &r.term("decides").unwrap().grad;
        let last = r.layout.var(0, r.layout.steps - 1, crate::cost::Coord::X);
        assert!(g.iter().any(|&(k, d)| k == last && d != 0.0), "{g:?}");
        // Agent 2 starts 10 m behind agent 1 in the next lane and 12 m/s faster: level at
        // 0.83 s, ahead from the step at 0.9 s; agent 1 never passes agent 2.
        let text = "steps: 41\ncurrent_step: 0\nroad: {lanes: 2, lane_width: 3.5, length: 300}\nagents:\n  - {id: 1, lane: 0, s: 50, speed: 10}\n  - {id: 2, lane: 1, s: 40, speed: 22}\n";
        let s = crate::io::yaml::parse(std::path::Path::new("t.yaml"), text).unwrap();
        let r = evaluate_recorded(
            "let p = agent(1).lane_path();
             let t = pass_time(agent(2), agent(1), p);
             let never = pass_time(agent(1), agent(2), p);
             term(\"t\", t + 0.0 * agent(1).x.last());
             term(\"never\", (if type_of(never) == \"()\" { 1.0 } else { 0.0 }) + 0.0 * agent(1).x.last());",
            s,
        );
        assert!(
            (r.term("t").unwrap().value - 0.9).abs() < 1e-9,
            "{:?}",
            r.terms
        );
        assert_eq!(r.term("never").unwrap().value, 1.0);
    }

    #[test]
    fn lane_ahead_measures_the_mapped_lane_to_the_end_of_the_road() {
        let scene = Rc::new(highway());
        let r = evaluate_recorded(
            "let a = agent(1);
             term(\"own\", lane_ahead(a.lane, a.current_x, a.current_y) + a.current_x + 0.0 * a.x.last());
             term(\"second\", lane_ahead(200, a.current_x, a.current_y) + a.current_x + 0.0 * a.x.last());",
            (*scene).clone(),
        );
        for t in &r.terms {
            assert!((t.value - 500.0).abs() < 0.5, "{}: {}", t.name, t.value);
        }
        let err = evaluation_error(
            "term(\"x\", lane_ahead(999, 0.0, 0.0) + 0.0 * agent(1).x.last());",
            scene,
        );
        assert!(err.to_string().contains("999"), "{err}");
    }

    #[test]
    fn the_farthest_corner_is_the_largest_corner_distance() {
        let scene = Rc::new(highway());
        let r = evaluate_recorded(
            "let a = agent(3);
             let m = a.corner_edge_distance(0);
             for i in 1..4 { let c = a.corner_edge_distance(i); m = m + relu(c - m); }
             term(\"gap\", abs(m - a.box_edge_distance).max());",
            (*scene).clone(),
        );
        assert!(r.terms[0].value < 1e-9, "{}", r.terms[0].value);
        let err = evaluation_error(
            "term(\"x\", agent(1).corner_edge_distance(4).sum());",
            scene,
        );
        assert!(
            err.to_string().contains("corner 4 is not 0, 1, 2 or 3"),
            "{err}"
        );
    }

    #[test]
    fn valid_count_counts_observed_future_steps() {
        let mut scene = highway();
        // Agent 2 leaves the recording 30 steps after the current one.
        let c = scene.meta.current_step;
        scene.agents[1].states[c + 31..].fill(crate::scene::AgentState::INVALID);
        let future = scene.num_future_steps() as f64;
        let r = evaluate_recorded(
            "term(\"one\", agent(1).x.valid_count() + 0.0 * agent(1).x.last());
             term(\"two\", agent(2).x.valid_count() + 0.0 * agent(1).x.last());",
            scene,
        );
        let got: Vec<f64> = r.terms.iter().map(|t| t.value).collect();
        assert_eq!(got, vec![future, 30.0]);
    }

    #[test]
    fn reference_lists_sections_and_modules() {
        let md = reference_markdown();
        for s in [
            "## Agents",
            "## Frenet frame",
            "## Lane graph",
            "## Interactions",
            "## Terms",
            "Module `behaviours`",
            "`end_in_lane(a, path, tol)`",
        ] {
            assert!(md.contains(s), "missing {s}");
        }
    }
}
