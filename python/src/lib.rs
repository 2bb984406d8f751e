//! `drivescript._native`: the Python face of the drivescript library. It parses Python values
//! into the library's types, calls the library, and converts the results back; every rule
//! (the sandbox, the limits, validation, the sampler's settings, the checkers) is the
//! library's, as in the CLI. Errors become Python exceptions with the CLI's text; a panic in
//! the library becomes a `RuntimeError` naming it, never an abort.

use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, AtomicU64, Ordering};
use std::sync::{Arc, Mutex};

use drivescript::cost::{BoundScript, CostError, CostReport, ParamValue, Params, ScriptSpec};
use drivescript::cost::{Limits, Trajectories, VarLayout};
use drivescript::eval::behaviors::{self, Behavior};
use drivescript::io::scene_output::SceneOutput;
use drivescript::io::{IoError, LoadOptions};
use drivescript::sample::{self as sampler, AttemptError, AttemptSpec, SampleConfig};
use numpy::ndarray::{Array2, Array3, Array4};
use numpy::{AllowTypeChange, IntoPyArray, PyArrayLikeDyn, PyUntypedArrayMethods};
use pyo3::create_exception;
use pyo3::exceptions::{
    PyException, PyFileNotFoundError, PyOSError, PyOverflowError, PyRuntimeError, PyTypeError,
    PyValueError,
};
use pyo3::prelude::*;
use pyo3::types::{PyBool, PyDict, PyFloat, PyInt, PyString};

// The CLI's allocator (src/main.rs): the engine allocates a series per operation, and with
// the system allocator a call from Python would be slower than `drivescript bench cost`.
#[global_allocator]
static GLOBAL: mimalloc::MiMalloc = mimalloc::MiMalloc;

create_exception!(
    drivescript,
    ScriptError,
    PyException,
    "A cost script failed to compile, validate or evaluate. The message is the CLI's; `file`, \
     `line` and `column` say where (None where the error has no such place)."
);

/// The longest name `CostScript.from_source` takes, characters (a path's length).
const MAX_NAME_CHARS: usize = 4096;

/// The most future steps a trajectory may have: `drivescript cost --horizon`'s bound.
const MAX_STEPS: usize = 10_000;

/// The most numbers one `evaluate_batch` takes (2 GiB of float64): a batch of 1,024 samples of
/// 24 agents over 1,000 steps is under a third of it.
const MAX_BATCH_VALUES: usize = 1 << 28;

/// Runs `f` with the GIL released, turning a panic into a `RuntimeError` that names it.
fn detached<T: Send>(
    py: Python<'_>,
    what: &str,
    f: impl FnOnce() -> PyResult<T> + Send,
) -> PyResult<T> {
    // On a thread with the stack scripts need: Python's own thread overflowed comparing or
    // printing arrays a script nested 5,000 deep, and the interpreter aborted.
    py.detach(|| {
        drivescript::cost::on_script_stack(|| {
            std::panic::catch_unwind(std::panic::AssertUnwindSafe(f))
        })
    })
    .unwrap_or_else(|payload| {
        Err(PyRuntimeError::new_err(drivescript::io::internal_error(
            &*payload, what,
        )))
    })
}

/// [`detached`] for work that can stop early: `f` runs on a thread of its own while this one
/// checks, every 50 ms, for a signal Python must handle (Ctrl-C's KeyboardInterrupt). When
/// one comes, `stop` is set, `f` is waited for (it stops starting new work) and the signal's
/// exception is raised: a long batch ignored Ctrl-C to its end.
fn detached_interruptible<T: Send>(
    py: Python<'_>,
    what: &str,
    f: impl FnOnce(&AtomicBool) -> PyResult<T> + Send,
) -> PyResult<T> {
    let stop = AtomicBool::new(false);
    let waiter = std::thread::current();
    std::thread::scope(|s| {
        // The stack scripts need (a default thread's 2 MB overflowed on nested arrays).
        let work = std::thread::Builder::new()
            .stack_size(drivescript::cost::SCRIPT_STACK_BYTES)
            .spawn_scoped(s, || {
                // On the library's pool, as `detached` runs: the sampler's parallel tensor
                // operations took rayon's global pool, whose threads a process forked from
                // this one (multiprocessing, a DataLoader's workers) never has: sampling
                // there waited for them forever.
                let r = drivescript::cost::on_script_stack(|| {
                    std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| f(&stop)))
                });
                waiter.unpark();
                r
            })
            .map_err(|e| PyRuntimeError::new_err(format!("{what}: cannot start a thread: {e}")))?;
        loop {
            let finished = py.detach(|| {
                std::thread::park_timeout(std::time::Duration::from_millis(50));
                work.is_finished()
            });
            if finished {
                break;
            }
            if let Err(signal) = py.check_signals() {
                stop.store(true, Ordering::Relaxed);
                py.detach(|| {
                    let _ = work.join();
                });
                return Err(signal);
            }
        }
        work.join().unwrap_or_else(Err).unwrap_or_else(|payload| {
            Err(PyRuntimeError::new_err(drivescript::io::internal_error(
                &*payload, what,
            )))
        })
    })
}

fn script_error(py: Python<'_>, e: &CostError) -> PyErr {
    let text = e.to_string();
    let nonzero = |n: usize| (n > 0).then_some(n);
    let (file, line, column) = match e {
        CostError::Shape { .. } | CostError::Param { .. } => return PyValueError::new_err(text),
        CostError::Read(_) => return PyOSError::new_err(text),
        CostError::Syntax {
            script,
            line,
            column,
            ..
        }
        | CostError::Runtime {
            script,
            line,
            column,
            ..
        }
        | CostError::Limit {
            script,
            line,
            column,
            ..
        } => (script, nonzero(*line), nonzero(*column)),
        CostError::Term { script, line, .. } => (script, nonzero(*line), None),
        CostError::NoFuture { script, .. } | CostError::NoTerms { script } => (script, None, None),
    };
    let err = ScriptError::new_err(text);
    let v = err.value(py);
    // Setting attributes on a fresh exception instance cannot fail short of memory.
    let _ = v.setattr("file", file.as_str());
    let _ = v.setattr("line", line);
    let _ = v.setattr("column", column);
    err
}

fn io_error(e: IoError) -> PyErr {
    match &e {
        IoError::Read { source, .. } if source.kind() == std::io::ErrorKind::NotFound => {
            PyFileNotFoundError::new_err(e.to_string())
        }
        IoError::Read { .. } | IoError::Write { .. } => PyOSError::new_err(e.to_string()),
        _ => PyValueError::new_err(e.to_string()),
    }
}

/// A value the caller gave, quoted in the message that refuses it as the CLI quotes a flag's:
/// its repr, at most 64 characters (with its length where longer) and control characters
/// escaped. An int Python will not write out (beyond 4,300 digits) is said by its size: its
/// str() raised inside the message, which printed "<unprintable int object>" and an ignored
/// exception's traceback on stderr; a 101-digit int or a 1,000-element list was quoted whole.
fn quoted(v: &Bound<'_, PyAny>) -> String {
    match v.repr().and_then(|r| r.extract::<String>()) {
        Ok(r) => drivescript::io::name::shown_counted(&r),
        Err(_) => match v
            .call_method0("bit_length")
            .and_then(|b| b.extract::<u64>())
        {
            Ok(bits) => format!("an integer of {bits} bits"),
            Err(_) => "a value that cannot be shown".to_string(),
        },
    }
}

/// A number argument, converted in the function rather than by pyo3 so that its errors name
/// the argument: pyo3 names it only in an exception note ("while processing 'index'"), which
/// Python before 3.11 never shows and `str(e)` leaves out, under "can't convert negative int
/// to unsigned" or "int too large to convert to float".
enum Arg<T> {
    /// The signature's default.
    Default(T),
    /// What the caller passed, not yet converted.
    Given(Py<PyAny>),
}

impl<'a, 'py, T> FromPyObject<'a, 'py> for Arg<T> {
    type Error = PyErr;
    fn extract(obj: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        Ok(Arg::Given(obj.to_owned().unbind()))
    }
}

/// The number types an [`Arg`] converts to.
trait ArgNumber: Sized + Copy {
    /// Converts `v`, whose type has been checked to be a number of this kind; `Err(())`
    /// where its value is out of this type's range.
    fn convert(v: &Bound<'_, PyAny>) -> Result<Self, ()>;
    /// Whether values of this type are whole numbers.
    const WHOLE: bool;
    /// The range, for messages.
    fn range() -> String;
}

macro_rules! whole_arg {
    ($($t:ty),*) => {$(
        impl ArgNumber for $t {
            fn convert(v: &Bound<'_, PyAny>) -> Result<Self, ()> {
                // Python's own conversion through __index__ (numpy integers too); a value
                // past i128 is out of every range here.
                let wide: i128 = v.extract().map_err(|_| ())?;
                <$t>::try_from(wide).map_err(|_| ())
            }
            const WHOLE: bool = true;
            fn range() -> String {
                format!("a whole number from {} to {}", <$t>::MIN, <$t>::MAX)
            }
        }
    )*};
}
whole_arg!(usize, u64, i64);

impl ArgNumber for f64 {
    fn convert(v: &Bound<'_, PyAny>) -> Result<Self, ()> {
        v.extract().map_err(|_| ())
    }
    const WHOLE: bool = false;
    fn range() -> String {
        "a number float64 holds".into()
    }
}

impl<T: ArgNumber> Arg<T> {
    /// The value, or an error naming the argument `name`: TypeError for what is not a number
    /// of this kind (a bool, a str, a float for a whole number), ValueError for a number out
    /// of range.
    fn get(&self, py: Python<'_>, name: &str) -> PyResult<T> {
        let v = match self {
            Arg::Default(v) => return Ok(*v),
            Arg::Given(v) => v.bind(py),
        };
        let kind_ok = !v.is_instance_of::<PyBool>()
            && if T::WHOLE {
                v.hasattr("__index__")?
            } else {
                !v.is_instance_of::<PyString>() && v.hasattr("__float__")?
                    || v.hasattr("__index__")?
            };
        if !kind_ok {
            return Err(PyTypeError::new_err(format!(
                "{name} = {}: a {}, but {name} is {}",
                quoted(v),
                v.get_type().name()?,
                if T::WHOLE {
                    "an int"
                } else {
                    "a number (float or int)"
                }
            )));
        }
        T::convert(v).map_err(|()| {
            PyValueError::new_err(format!("{name} = {}: must be {}", quoted(v), T::range()))
        })
    }
}

/// [`Arg::get`] for an optional argument.
fn opt<T: ArgNumber>(py: Python<'_>, a: &Option<Arg<T>>, name: &str) -> PyResult<Option<T>> {
    a.as_ref().map(|a| a.get(py, name)).transpose()
}

/// A str argument, converted in the function so that its errors name it: a str holding a lone
/// surrogate (what `os.fsdecode` or `errors="surrogateescape"` make of bytes that are not
/// UTF-8) raised pyo3's UnicodeEncodeError, "'utf-8' codec can't encode character", which
/// names no argument.
enum Text {
    /// The signature's default.
    Default(&'static str),
    /// What the caller passed, not yet converted.
    Given(Py<PyAny>),
}

impl<'a, 'py> FromPyObject<'a, 'py> for Text {
    type Error = PyErr;
    fn extract(obj: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        Ok(Text::Given(obj.to_owned().unbind()))
    }
}

impl Text {
    /// The text, or an error naming the argument `name`: TypeError for what is not a str,
    /// ValueError for a str that is not text.
    fn get(&self, py: Python<'_>, name: &str) -> PyResult<String> {
        let v = match self {
            Text::Default(s) => return Ok((*s).to_string()),
            Text::Given(v) => v.bind(py),
        };
        if !v.is_instance_of::<PyString>() {
            return Err(PyTypeError::new_err(format!(
                "{name} = {}: a {}, but {name} is a str",
                quoted(v),
                v.get_type().name()?
            )));
        }
        v.extract::<String>().map_err(|_| {
            PyValueError::new_err(format!(
                "{name} = {}: holds a lone surrogate, which is not text (a str decoded from \
                 bytes that are not UTF-8)",
                quoted(v)
            ))
        })
    }
}

/// A path argument as Python's own file functions take one: a str, bytes or os.PathLike
/// (pyo3's PathBuf took str only, after os.fspath's TypeError had said "expected str, bytes or
/// os.PathLike object": bytes were then refused as "'bytes' object is not an instance of
/// 'str'"). Converted with os.fsencode, so a name os.listdir gave as bytes, or as str with
/// surrogate escapes, is the file's.
struct PathArg(PathBuf);

impl<'a, 'py> FromPyObject<'a, 'py> for PathArg {
    type Error = PyErr;
    fn extract(obj: Borrowed<'a, 'py, PyAny>) -> PyResult<Self> {
        let py = obj.py();
        let bytes: Vec<u8> = py
            .import("os")?
            .call_method1("fsencode", (obj.to_owned(),))?
            .extract()?;
        #[cfg(unix)]
        let path = {
            use std::os::unix::ffi::OsStringExt;
            PathBuf::from(std::ffi::OsString::from_vec(bytes))
        };
        #[cfg(not(unix))]
        let path = PathBuf::from(
            String::from_utf8(bytes)
                .map_err(|e| PyValueError::new_err(format!("a path that is not UTF-8: {e}")))?,
        );
        Ok(PathArg(path))
    }
}

/// Refuses a path holding a NUL character, which no file's path can hold: it was read as far
/// as the format check, which called `scene.yaml\0x` an unknown scene format and printed the
/// NUL raw in the message.
fn no_nul(path: &std::path::Path, arg: &str) -> PyResult<()> {
    if path.as_os_str().as_encoded_bytes().contains(&0) {
        return Err(PyValueError::new_err(format!(
            "{arg} = \"{}\": a path cannot hold the NUL character (\\u{{0000}})",
            drivescript::io::name::shown_counted(&path.to_string_lossy())
        )));
    }
    Ok(())
}

fn params_from(dict: Option<&Bound<'_, PyDict>>) -> PyResult<Params> {
    let mut out = Params::default();
    for (k, v) in dict.into_iter().flat_map(|d| d.iter()) {
        // A str that is no UTF-8 (a lone surrogate, as os.fsdecode makes of bytes that are
        // not text) was said to be no string, or raised UnicodeEncodeError naming no parameter.
        let name: String = k.extract().map_err(|_| {
            PyValueError::new_err(if k.is_instance_of::<PyString>() {
                format!(
                    "parameter name {}: holds a lone surrogate, which is not text",
                    quoted(&k)
                )
            } else {
                format!("parameter names are strings, got {}", quoted(&k))
            })
        })?;
        // bool before int: Python's True is an int too.
        let value = if v.is_instance_of::<PyBool>() {
            ParamValue::Bool(v.extract()?)
        } else if v.is_instance_of::<PyInt>()
            // NumPy's integers (an id taken from an array of them) are ints to Python's
            // __index__, as every whole-number argument here takes them; they were refused as
            // "not an int, float, bool or str".
            || (!v.is_instance_of::<PyFloat>() && v.hasattr("__index__")?)
        {
            ParamValue::Int(v.extract().map_err(|_| {
                PyValueError::new_err(format!(
                    "parameter {name:?} = {}: out of the 64-bit range",
                    quoted(&v)
                ))
            })?)
        } else if v.is_instance_of::<PyFloat>() {
            ParamValue::Float(v.extract()?)
        } else if v.is_instance_of::<PyString>() {
            ParamValue::Str(v.extract().map_err(|_| {
                PyValueError::new_err(format!(
                    "parameter {name:?} = {}: holds a lone surrogate, which is not text",
                    quoted(&v)
                ))
            })?)
        } else {
            return Err(PyValueError::new_err(format!(
                "parameter {name:?} = {}: a parameter is an int, float, bool or str",
                quoted(&v)
            )));
        };
        // The library's checks, as `--param` gets them: a NaN limit, a name no script can
        // read or a value with control characters is refused here too.
        out.push_checked(&name, value).map_err(|m| {
            PyValueError::new_err(format!(
                "parameter \"{}\": {m}",
                drivescript::io::name::shown(&name)
            ))
        })?;
    }
    Ok(out)
}

fn params_to<'py>(py: Python<'py>, p: &Params) -> PyResult<Bound<'py, PyDict>> {
    let d = PyDict::new(py);
    for (k, v) in &p.0 {
        match v {
            ParamValue::Int(i) => d.set_item(k, i)?,
            ParamValue::Float(f) => d.set_item(k, f)?,
            ParamValue::Bool(b) => d.set_item(k, b)?,
            ParamValue::Str(s) => d.set_item(k, s)?,
        }
    }
    Ok(d)
}

/// The shape an array must have, in words, for error messages.
fn wanted(scene: &Scene, batch: bool) -> String {
    format!(
        "expected shape ({}{}, steps, 3): x, y, heading of each of the scene's {} agents \
         (in agent_ids order) at each future step, float64, NaN where unobserved",
        if batch { "batch, " } else { "" },
        scene.inner.agents.len(),
        scene.inner.agents.len()
    )
}

/// Reads `[agents, steps, 3]` (or `[batch, agents, steps, 3]`) from any array-like into
/// trajectories over `steps` future steps of `scene`.
/// `obj` as float64 numbers. Integers and floats of any width convert; numpy's own conversion
/// would also take complex numbers (dropping the imaginary part with only a warning), booleans
/// and numeric strings, none of which is a position, so those are refused.
fn floats<'py>(
    what: &str,
    wanted: &str,
    obj: &Bound<'py, PyAny>,
) -> PyResult<PyArrayLikeDyn<'py, f64, AllowTypeChange>> {
    let py = obj.py();
    let np = py.import("numpy")?;
    // numpy's asarray keeps a masked array's data and drops its mask: the values under the
    // mask (whatever was left there) were read as positions, without a word.
    if obj.is_instance(&np.getattr("ma")?.getattr("MaskedArray")?)? {
        let masked: usize = np
            .getattr("ma")?
            .call_method1("count_masked", (obj,))?
            .extract()?;
        if masked > 0 {
            return Err(PyValueError::new_err(format!(
                "{what}: a masked array with {masked} masked values, which would be read as \
                 the positions they hide: give unobserved states as NaN \
                 ({what}.filled(numpy.nan))"
            )));
        }
    }
    // Nested lists of uneven lengths: numpy's "setting an array element with a sequence. The
    // requested array has an inhomogeneous shape" named neither the argument nor the shape
    // wanted.
    let arr = np.call_method1("asarray", (obj,)).map_err(|e| {
        if !e.is_instance_of::<PyValueError>(py) {
            return e;
        }
        let err = PyValueError::new_err(format!(
            "{what}: not an array of one shape ({}): {wanted}",
            e.value(py)
        ));
        err.set_cause(py, Some(e));
        err
    })?;
    let dtype = arr.getattr("dtype")?;
    let kind: String = dtype.getattr("kind")?.extract()?;
    // 'O' (Python objects, a list mixing types) converts element by element with float(),
    // which took the strings "1.0" and b"1.0", True and None for positions (None as NaN)
    // that an array of strings, booleans or no values is refused as: each must be a number.
    if kind == "O" {
        let real = py.import("numbers")?.getattr("Real")?;
        let decimal = py.import("decimal")?.getattr("Decimal")?;
        let np_bool = np.getattr("bool_")?;
        let float = py.import("builtins")?.getattr("float")?;
        for (i, x) in arr.call_method0("ravel")?.try_iter()?.enumerate() {
            let x = x?;
            let number = !x.is_instance_of::<PyBool>()
                && !x.is_instance(&np_bool)?
                && (x.is_instance(&real)? || x.is_instance(&decimal)?);
            let at = || -> PyResult<Vec<usize>> {
                np.call_method1("unravel_index", (i, arr.getattr("shape")?))?
                    .extract()
            };
            if !number {
                return Err(PyTypeError::new_err(format!(
                    "{what}: the element at {:?} is {} of type {}, but positions and \
                     headings are real numbers (float or int; NaN where unobserved)",
                    at()?,
                    quoted(&x),
                    x.get_type().name()?
                )));
            }
            // An int past float64's range (10**400) failed in numpy's conversion below with
            // only "int too large to convert to float", naming no element.
            if let Err(e) = float.call1((&x,)) {
                let err = PyOverflowError::new_err(format!(
                    "{what}: the element at {:?} is {}, which no float64 holds ({})",
                    at()?,
                    quoted(&x),
                    e.value(py)
                ));
                err.set_cause(py, Some(e));
                return Err(err);
            }
        }
    }
    if !matches!(kind.as_str(), "f" | "i" | "u" | "O") {
        return Err(PyTypeError::new_err(format!(
            "{what}: an array of {} ({}), but positions and headings are real numbers \
             (float or int)",
            dtype.str()?,
            match kind.as_str() {
                "c" => "complex numbers",
                "b" => "booleans",
                "U" | "S" => "strings",
                "M" | "m" => "dates or durations",
                _ => "values that are not numbers",
            }
        )));
    }
    arr.extract()
}

fn trajectories(
    scene: &Scene,
    obj: &Bound<'_, PyAny>,
    batch: bool,
) -> PyResult<(usize, Vec<Trajectories>)> {
    let arr = &floats(
        if batch { "trajs" } else { "traj" },
        &wanted(scene, batch),
        obj,
    )?;
    let shape = arr.shape().to_vec();
    let agents = scene.inner.agents.len();
    let dims = if batch { 4 } else { 3 };
    let fits = shape.len() == dims
        && agents >= 1
        && shape[dims - 3] == agents
        && shape[dims - 1] == 3
        && (1..=MAX_STEPS).contains(&shape[dims - 2])
        && (!batch || shape[0] >= 1);
    if !fits {
        return Err(PyValueError::new_err(format!(
            "trajectories of shape {shape:?}: {} (steps 1 to {MAX_STEPS}{})",
            wanted(scene, batch),
            if batch { ", batch at least 1" } else { "" }
        )));
    }
    let steps = shape[dims - 2];
    let layout = VarLayout { agents, steps };
    // A batch view that holds no memory (`np.broadcast_to(traj, (10**9, ...))`) is copied
    // item by item, and each item gets a gradient as large: the process grew until the
    // system's OOM killer ended it (or another program), with no exception.
    if batch && shape[0] > MAX_BATCH_VALUES / layout.len() {
        let per = (MAX_BATCH_VALUES / layout.len()).max(1);
        return Err(PyValueError::new_err(format!(
            "trajectories of shape {shape:?}: {} items of {} numbers, more than evaluate_batch \
             takes at once ({MAX_BATCH_VALUES} numbers, 2 GiB of float64, copied and given a \
             gradient each): evaluate it in parts of at most {per} items",
            shape[0],
            layout.len()
        )));
    }
    // A C-contiguous float64 array (what numpy and torch hand over) is read in place; any
    // other (Fortran order, a strided view) in logical order.
    let copied: Vec<f64>;
    let values = match arr.as_slice() {
        Ok(v) if arr.is_c_contiguous() => v,
        _ => {
            copied = arr.as_array().iter().copied().collect();
            &copied
        }
    };
    let out = values
        .chunks_exact(layout.len())
        .enumerate()
        .map(|(b, v)| {
            Trajectories::from_array(layout, v).map_err(|m| {
                let at = if batch {
                    format!("batch item {b}, ")
                } else {
                    String::new()
                };
                PyValueError::new_err(format!("trajectories: {at}{m}"))
            })
        })
        .collect::<PyResult<Vec<_>>>()?;
    Ok((steps, out))
}

static NEXT_SCENE: AtomicU64 = AtomicU64::new(1);

/// A traffic scene: a road map and its agents' states at a fixed time step, read from any
/// format the CLI reads (CommonRoad XML, Argoverse 2 parquet directories, WOMD TFRecords,
/// GPUDrive/Nocturne scenario JSON, drivescript YAML).
#[pyclass(frozen, module = "drivescript")]
struct Scene {
    inner: Arc<drivescript::scene::Scene>,
    uid: u64,
}

impl Scene {
    fn wrap(inner: drivescript::scene::Scene) -> Self {
        Self {
            inner: Arc::new(inner),
            uid: NEXT_SCENE.fetch_add(1, Ordering::Relaxed),
        }
    }

    /// The scene over `steps` future steps (default: the recorded ones).
    fn over(&self, steps: Option<usize>) -> PyResult<drivescript::scene::Scene> {
        Ok(self.inner.over_horizon(self.horizon(steps)?))
    }

    /// `steps` future steps, checked (default: the recorded ones).
    fn horizon(&self, steps: Option<usize>) -> PyResult<usize> {
        let steps = match steps {
            Some(n) => n,
            // "steps = 0" would blame an argument the caller did not give.
            None if self.inner.num_future_steps() == 0 => {
                return Err(PyValueError::new_err(format!(
                    "scene {:?} records no step after its current step {}: give steps",
                    self.inner.meta.scenario_id, self.inner.meta.current_step
                )))
            }
            None => self.inner.num_future_steps(),
        };
        if !(1..=MAX_STEPS).contains(&steps) {
            return Err(PyValueError::new_err(format!(
                "steps = {steps}: must be 1 to {MAX_STEPS}"
            )));
        }
        Ok(steps)
    }
}

/// Trajectories as float64 `[agents, steps, 3]`, NaN where unobserved.
fn array3<'py>(py: Python<'py>, t: &Trajectories) -> PyResult<Bound<'py, PyAny>> {
    let l = t.layout;
    let a = Array3::from_shape_vec((l.agents, l.steps, 3), t.to_array())
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py).into_any())
}

/// Points as float64 `[points, 2]`.
fn points2<'py>(py: Python<'py>, pts: &[drivescript::geom::Point]) -> PyResult<Bound<'py, PyAny>> {
    let values: Vec<f64> = pts.iter().flat_map(|p| [p.x, p.y]).collect();
    let a = Array2::from_shape_vec((pts.len(), 2), values)
        .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
    Ok(a.into_pyarray(py).into_any())
}

/// A lane path's length in metres: (0, 100000], as the scripts' `lane_path` takes.
fn path_length(length: f64) -> PyResult<()> {
    if length.is_finite() && length > 0.0 && length <= 100_000.0 {
        Ok(())
    } else {
        Err(PyValueError::new_err(format!(
            "length {}: must be in (0, 100000] metres",
            drivescript::geom::num(length)
        )))
    }
}

/// A turn at forks from its word, as scripts spell it.
fn turn_word(w: &str) -> PyResult<drivescript::scene::Turn> {
    drivescript::scene::Turn::from_word(w).ok_or_else(|| {
        PyValueError::new_err(format!(
            "turn {w:?}: give \"straight\", \"left\" or \"right\""
        ))
    })
}

#[pymethods]
impl Scene {
    /// Reads scene number `index` of `path` (a file or a directory, as `drivescript cost`
    /// takes it). `commonroad_current_step` is the current step given to CommonRoad scenes,
    /// which have none of their own (left out: 10, 1 s of history at 10 Hz, or the last step
    /// of a shorter scene). Given, it must leave at least one future step.
    ///
    /// Raises FileNotFoundError or OSError where the file cannot be read, ValueError where
    /// it is not a valid scene (the message names the file and the record).
    #[staticmethod]
    #[pyo3(signature = (path, index = Arg::Default(0), commonroad_current_step = None))]
    fn load(
        py: Python<'_>,
        path: PathArg,
        index: Arg<usize>,
        commonroad_current_step: Option<Arg<usize>>,
    ) -> PyResult<Self> {
        let index = index.get(py, "index")?;
        let commonroad_current_step = opt(py, &commonroad_current_step, "commonroad_current_step")?;
        let path = path.0;
        no_nul(&path, "path")?;
        let opts = LoadOptions {
            commonroad_current_step: commonroad_current_step
                .unwrap_or(LoadOptions::default().commonroad_current_step),
        };
        let scene = detached(py, "scene reader", || {
            drivescript::io::load_scene(&path, index, &opts)
                .map(Scene::wrap)
                .map_err(io_error)
        })?;
        // The reader clamps to the scene's last step: asked for in so many words, step 1000
        // of a 32-step scene came back as step 31 with no future, without a word (and step
        // 2**64 - 1 still did, its `k + 1` wrapping to 0).
        let meta = &scene.inner.meta;
        if commonroad_current_step.is_some()
            && meta.source_format != drivescript::scene::SourceFormat::CommonRoad
        {
            // Other formats carry their own current step: the argument was ignored unsaid.
            return Err(PyValueError::new_err(format!(
                "{}: commonroad_current_step applies to CommonRoad scenes only; this {} scene \
                 has its own current step ({})",
                path.display(),
                meta.source_format.name(),
                meta.current_step
            )));
        }
        if let Some(k) = commonroad_current_step {
            let n = scene.inner.num_steps();
            if meta.source_format == drivescript::scene::SourceFormat::CommonRoad
                && k.saturating_add(1) >= n
            {
                return Err(PyValueError::new_err(format!(
                    "{}: commonroad_current_step {k} leaves no future (the scene has {n} steps: \
                     give 0 to {})",
                    path.display(),
                    n.saturating_sub(2)
                )));
            }
        }
        Ok(scene)
    }

    /// The agents' ids, in the order of the agent axis of every trajectory array.
    #[getter]
    fn agent_ids(&self) -> Vec<i64> {
        self.inner.agents.iter().map(|a| a.id).collect()
    }

    /// Seconds per step.
    #[getter]
    fn dt(&self) -> f64 {
        self.inner.meta.dt
    }

    /// Index of the current step: history up to it, future after it.
    #[getter]
    fn current_step(&self) -> usize {
        self.inner.meta.current_step
    }

    /// Steps recorded after the current one (the default of `log_future`).
    #[getter]
    fn future_steps(&self) -> usize {
        self.inner.num_future_steps()
    }

    /// The scenario's id.
    #[getter]
    fn scenario_id(&self) -> &str {
        &self.inner.meta.scenario_id
    }

    /// The recorded future, float64 `[agents, steps, 3]`: x, y (metres) and heading
    /// (radians) of each agent at each of the `steps` steps after the current one (default:
    /// every recorded one), NaN where the agent is unobserved (including past the recording).
    #[pyo3(signature = (steps = None))]
    fn log_future<'py>(
        &self,
        py: Python<'py>,
        steps: Option<Arg<usize>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let scene = self.over(opt(py, &steps, "steps")?)?;
        array3(py, &Trajectories::recorded(&scene))
    }

    /// The recorded future as `log_future` gives it, with every unobserved state filled in:
    /// at constant velocity from the agent's latest observed state (its first one, held,
    /// before it is first seen). A complete starting point for optimisation, and the
    /// trajectories `drivescript bench cost` times.
    #[pyo3(signature = (steps = None))]
    fn filled_future<'py>(
        &self,
        py: Python<'py>,
        steps: Option<Arg<usize>>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let scene = self.over(opt(py, &steps, "steps")?)?;
        array3(py, &Trajectories::filled(&scene))
    }

    /// Each agent's footprint, float64 `[agents, 2]`: length and width in metres (what a
    /// script reads as `a.length` and `a.width`; box clearances use them).
    #[getter]
    fn agent_sizes<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let values: Vec<f64> = self
            .inner
            .agents
            .iter()
            .flat_map(|a| [a.length, a.width])
            .collect();
        let a = Array2::from_shape_vec((self.inner.agents.len(), 2), values)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py).into_any())
    }

    /// Each agent's type: "vehicle", "pedestrian", "cyclist" or "other" (`a.type`;
    /// `vehicles()` in a script is the agents of type "vehicle").
    #[getter]
    fn agent_types(&self) -> Vec<&'static str> {
        self.inner
            .agents
            .iter()
            .map(|a| a.agent_type.name())
            .collect()
    }

    /// The centre line, float64 `[points, 2]`, of the path a script's
    /// `lane_path(lane, length, turn)` gives: `lane` extended through its successors to
    /// `length` metres from its start (taking `turn`, "straight", "left" or "right", at
    /// forks) and 50 m back through its predecessors. Frenet coordinates (`a.frenet(path)`)
    /// are measured along this polyline, s from its first point.
    ///
    /// Raises ValueError for an unknown lane, a length outside (0, 100000] or another turn.
    #[pyo3(signature = (lane, length, turn = Text::Default("straight")))]
    fn lane_path<'py>(
        &self,
        py: Python<'py>,
        lane: Arg<i64>,
        length: Arg<f64>,
        turn: Text,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (lane, length) = (lane.get(py, "lane")?, length.get(py, "length")?);
        let turn = turn_word(&turn.get(py, "turn")?)?;
        path_length(length)?;
        let path = self
            .inner
            .map
            .lane_path(lane, length, 50.0, turn)
            .map_err(|e| PyValueError::new_err(format!("lane {lane}: {e}")))?;
        points2(py, path.frenet.polyline().points())
    }

    /// The centre line, float64 `[points, 2]`, of the path a script's
    /// `a.lane_path(length, turn)` gives for agent `agent_id`: its lane at the current step,
    /// from 50 m behind that lane's start to `length` metres ahead of the agent (default
    /// 300, as `a.lane_path()`).
    ///
    /// Raises ValueError for an unknown agent, one not observed at the current step or near
    /// no lane going its way, a length outside (0, 100000] or a turn other than "straight",
    /// "left" and "right".
    #[pyo3(signature = (agent_id, length = Arg::Default(300.0), turn = Text::Default("straight")))]
    fn agent_lane_path<'py>(
        &self,
        py: Python<'py>,
        agent_id: Arg<i64>,
        length: Arg<f64>,
        turn: Text,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (agent_id, length) = (agent_id.get(py, "agent_id")?, length.get(py, "length")?);
        let turn = turn_word(&turn.get(py, "turn")?)?;
        path_length(length)?;
        let idx = self
            .inner
            .agents
            .iter()
            .position(|a| a.id == agent_id)
            .ok_or_else(|| PyValueError::new_err(format!("no agent {agent_id} in the scene")))?;
        let path = self
            .inner
            .agent_lane_path(idx, length, 50.0, turn)
            .ok_or_else(|| {
                PyValueError::new_err(format!(
                    "agent {agent_id} is not observed at the current step or is near no lane going its way"
                ))
            })?;
        points2(py, path.frenet.polyline().points())
    }

    /// At most `agents` agents observed at the current step, with exactly `future` steps
    /// after it: vehicles on a lane first, nearest first to the first such vehicle, then the
    /// other agents. A recording too short after its current step has its current step moved
    /// earlier. `Scene.load(p).crop(24, 80)` is the scene `drivescript bench cost` times.
    ///
    /// Raises ValueError where the scene is shorter than `future + 1` steps or no observed
    /// vehicle is on a lane.
    fn crop(&self, py: Python<'_>, agents: Arg<usize>, future: Arg<usize>) -> PyResult<Self> {
        let (agents, future) = (agents.get(py, "agents")?, future.get(py, "future")?);
        self.inner
            .crop(agents, future)
            .map(Scene::wrap)
            .map_err(|e| PyValueError::new_err(e.to_string()))
    }

    /// The recorded history up to and including the current step, float64
    /// `[agents, current_step + 1, 3]` (x, y, heading), NaN where unobserved.
    fn log_history<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyAny>> {
        let n = self.inner.meta.current_step + 1;
        let values: Vec<f64> = self
            .inner
            .agents
            .iter()
            .flat_map(|a| a.states[..n].iter())
            .flat_map(|s| {
                if s.valid {
                    [s.x, s.y, s.heading]
                } else {
                    [f64::NAN; 3]
                }
            })
            .collect();
        let a = Array3::from_shape_vec((self.inner.agents.len(), n, 3), values)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py).into_any())
    }

    /// Writes `traj` (float64 `[agents, steps, 3]`, NaN where unobserved) as this scene's
    /// future to `path`, atomically, in the rollout JSON format that `drivescript cost
    /// --rollout`, `eval --rollouts` and `render` read.
    fn write_rollout(&self, py: Python<'_>, path: PathArg, traj: Bound<'_, PyAny>) -> PyResult<()> {
        let path = path.0;
        no_nul(&path, "path")?;
        // `convert -o` picks the format by the extension: JSON under r.yaml was a file that
        // every reader of YAML refuses.
        if SceneOutput::from_path(&path) != Some(SceneOutput::Rollout) {
            return Err(PyValueError::new_err(format!(
                "path {}: a rollout is JSON: give a name ending in .json",
                path.display()
            )));
        }
        let (_, mut t) = trajectories(self, &traj, false)?;
        let t = t.remove(0);
        let inner = self.inner.clone();
        detached(py, "rollout writer", move || {
            // As `convert -o x.json`: an earlier rollout may be replaced, any other file (the
            // scene this came from, a user's notes) is theirs.
            SceneOutput::Rollout
                .check_replaces_own(&path, "write_rollout")
                .map_err(io_error)?;
            let scene = t.applied_to(&inner).map_err(PyValueError::new_err)?;
            drivescript::io::rollout::Rollout::from_scene(&scene)
                .write(&path)
                .map_err(io_error)
        })
    }

    fn __repr__(&self) -> String {
        format!(
            "Scene({:?}: {} agents, dt {} s, current step {}, {} future steps)",
            self.inner.meta.scenario_id,
            self.inner.agents.len(),
            self.inner.meta.dt,
            self.inner.meta.current_step,
            self.inner.num_future_steps()
        )
    }
}

/// What one evaluation of a cost script gives: the weighted total, each term's (unweighted)
/// value and weight, the total's gradient w.r.t. every trajectory coordinate (shaped like
/// the trajectories; 0 where unobserved) and what the script printed.
#[pyclass(frozen, module = "drivescript")]
struct CostResult {
    /// The weighted total, sum over terms of weight x value.
    #[pyo3(get)]
    total: f64,
    terms: Vec<(String, f64, f64)>,
    /// d total / d trajectories: float64 `[agents, steps, 3]`.
    #[pyo3(get)]
    grad: Py<PyAny>,
    /// Lines the script printed.
    #[pyo3(get)]
    prints: Vec<String>,
    /// Milliseconds the evaluation took inside the engine.
    #[pyo3(get)]
    eval_ms: f64,
}

impl CostResult {
    /// A dict of term name -> `pick(term)`.
    fn by_name<'py>(
        &self,
        py: Python<'py>,
        pick: impl Fn(&(String, f64, f64)) -> f64,
    ) -> PyResult<Bound<'py, PyDict>> {
        let d = PyDict::new(py);
        for t in &self.terms {
            d.set_item(&t.0, pick(t))?;
        }
        Ok(d)
    }

    fn new(py: Python<'_>, r: CostReport) -> PyResult<Self> {
        let l = r.layout;
        let grad = Array3::from_shape_vec((l.agents, l.steps, 3), r.gradient)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(Self {
            total: r.total,
            terms: r
                .terms
                .iter()
                .map(|t| (t.name.clone(), t.value, t.weight))
                .collect(),
            grad: grad.into_pyarray(py).into_any().unbind(),
            prints: r.prints,
            eval_ms: r.elapsed.as_secs_f64() * 1000.0,
        })
    }
}

#[pymethods]
impl CostResult {
    /// Each term's unweighted value, by name, in declaration order.
    #[getter]
    fn terms<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        self.by_name(py, |(_, value, _)| *value)
    }

    /// Each term's weight, by name.
    #[getter]
    fn weights<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        self.by_name(py, |(_, _, weight)| *weight)
    }

    fn __repr__(&self) -> String {
        // Six decimals of 2e302 (positions of 1e300) printed 309 digits.
        let shown = |v: f64| {
            if v.is_finite() && (v.abs() >= 1e7 || (v != 0.0 && v.abs() < 1e-6)) {
                format!("{v:.6e}")
            } else {
                format!("{v:.6}")
            }
        };
        let terms: Vec<String> = self
            .terms
            .iter()
            .map(|(n, v, _)| format!("{n}={}", shown(*v)))
            .collect();
        format!(
            "CostResult(total={}, {})",
            shown(self.total),
            terms.join(", ")
        )
    }
}

/// Scripts bound per (scene, steps) that a `CostScript` keeps: a few scenes at a time.
const BOUND_PER_SCRIPT: usize = 8;

/// A Rhai cost script with its parameters: sandboxed and limited as in the CLI, compiled and
/// validated against each scene (and horizon) it is first evaluated on.
///
/// `evaluate(scene, traj)` gives a `CostResult` (total, terms, gradient);
/// `evaluate_batch(scene, trajs)` evaluates many in parallel with the GIL released. Errors in
/// the script raise `ScriptError` with the CLI's message.
#[pyclass(frozen, module = "drivescript")]
struct CostScript {
    spec: ScriptSpec,
    bound: Mutex<Vec<(u64, usize, Arc<BoundScript>)>>,
}

impl CostScript {
    fn with_spec(spec: ScriptSpec) -> Self {
        Self {
            spec,
            bound: Mutex::new(Vec::new()),
        }
    }

    /// The script bound to `scene` over `steps` future steps, compiled and validated (with the
    /// GIL released) the first time.
    fn bound(&self, py: Python<'_>, scene: &Scene, steps: usize) -> PyResult<Arc<BoundScript>> {
        let key = (scene.uid, steps);
        let hit = |v: &Vec<(u64, usize, Arc<BoundScript>)>| {
            v.iter()
                .find(|(u, s, _)| (*u, *s) == key)
                .map(|e| e.2.clone())
        };
        if let Some(b) = hit(&self.bound.lock().unwrap_or_else(|p| p.into_inner())) {
            return Ok(b);
        }
        let (spec, inner) = (self.spec.clone(), scene.inner.clone());
        let made = detached(py, "cost script", move || {
            Ok(BoundScript::new(spec, inner.over_horizon(steps)))
        })?;
        let b = Arc::new(made.map_err(|e| script_error(py, &e))?);
        let mut v = self.bound.lock().unwrap_or_else(|p| p.into_inner());
        if v.len() >= BOUND_PER_SCRIPT {
            v.remove(0);
        }
        v.push((key.0, key.1, b.clone()));
        Ok(b)
    }
}

#[pymethods]
impl CostScript {
    /// Reads the script in `path` (a regular UTF-8 file of at most 64 KiB) with `params`
    /// (name -> int | float | bool | str), visible to the script as constants. A parameter
    /// the script does not use is a ValueError, as `--param` is in the CLI.
    #[staticmethod]
    #[pyo3(signature = (path, params = None))]
    fn from_file(
        py: Python<'_>,
        path: PathArg,
        params: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let path = path.0;
        no_nul(&path, "path")?;
        let params = params_from(params)?;
        ScriptSpec::from_file(&path, params)
            .map(Self::with_spec)
            .map_err(|e| script_error(py, &e))
    }

    /// A script from its source text, named `name` in messages.
    #[staticmethod]
    #[pyo3(signature = (source, name = Text::Default("<script>"), params = None))]
    fn from_source(
        py: Python<'_>,
        source: Text,
        name: Text,
        params: Option<&Bound<'_, PyDict>>,
    ) -> PyResult<Self> {
        let (source, name) = (source.get(py, "source")?, name.get(py, "name")?);
        let name = name.as_str();
        // The name starts every error message: one of 100,000 characters made every message
        // as long.
        let chars = name.chars().count();
        if chars > MAX_NAME_CHARS {
            return Err(PyValueError::new_err(format!(
                "name {}: {chars} characters; a script's name starts its error messages, so it \
                 is at most {MAX_NAME_CHARS}",
                drivescript::io::name::shown_counted(name)
            )));
        }
        // The name starts every error message: a newline in it faked a line of its own
        // ("evil\nerror: all good:1:29: ..."), as a scenario id's once did.
        if let Err(c) = drivescript::io::name::check_name(name) {
            return Err(PyValueError::new_err(format!(
                "name {}: holds {c}; a script's name starts its error messages",
                drivescript::io::name::shown(name)
            )));
        }
        // An empty name began every message with a bare place, ":1:1: syntax error: ...".
        if name.trim().is_empty() {
            return Err(PyValueError::new_err(format!(
                "name {:?}: is blank; a script's name starts its error messages (the \
                 default is \"<script>\")",
                name
            )));
        }
        let spec = ScriptSpec::new(source, name, params_from(params)?);
        drivescript::cost::check_params(&[&spec.source], &spec.params)
            .and_then(|_| spec.check_syntax())
            .map(|_| Self::with_spec(spec))
            .map_err(|e| script_error(py, &e))
    }

    /// The name used in messages (the path for `from_file`).
    #[getter]
    fn name(&self) -> &str {
        &self.spec.name
    }

    /// The source text.
    #[getter]
    fn source(&self) -> &str {
        &self.spec.source
    }

    /// The parameters, name -> value.
    #[getter]
    fn params<'py>(&self, py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
        params_to(py, &self.spec.params)
    }

    /// Evaluates the script on `traj`, float64 `[agents, steps, 3]` (x, y, heading per agent
    /// in `scene.agent_ids` order and future step; NaN where unobserved), with the scene
    /// over `steps` future steps as `drivescript cost --horizon steps` takes it.
    fn evaluate(
        &self,
        py: Python<'_>,
        scene: &Scene,
        traj: Bound<'_, PyAny>,
    ) -> PyResult<CostResult> {
        let (steps, mut t) = trajectories(scene, &traj, false)?;
        let bound = self.bound(py, scene, steps)?;
        let t = t.remove(0);
        let r = detached(py, "cost script", move || Ok(bound.evaluate(&t)))?;
        CostResult::new(py, r.map_err(|e| script_error(py, &e))?)
    }

    /// Evaluates `trajs`, float64 `[batch, agents, steps, 3]`, in parallel on every core with
    /// the GIL released; one `CostResult` per batch item. The first item that fails raises
    /// its error, with `batch_index` set on it.
    fn evaluate_batch(
        &self,
        py: Python<'_>,
        scene: &Scene,
        trajs: Bound<'_, PyAny>,
    ) -> PyResult<Vec<CostResult>> {
        let (steps, t) = trajectories(scene, &trajs, true)?;
        let bound = self.bound(py, scene, steps)?;
        let reports = detached_interruptible(py, "cost script", move |stop| {
            // Stopped only with a signal pending, which is raised instead.
            Ok(bound
                .evaluate_batch_until(&t, stop)
                .unwrap_or_else(|| Ok(Vec::new())))
        })?;
        let reports = reports.map_err(|(k, e)| {
            let err = script_error(py, &e);
            let _ = err.value(py).setattr("batch_index", k);
            err
        })?;
        reports
            .into_iter()
            .map(|r| CostResult::new(py, r))
            .collect()
    }

    fn __repr__(&self) -> String {
        format!(
            "CostScript({:?}, params={})",
            self.spec.name, self.spec.params
        )
    }
}

/// The guided diffusion sampler with a trained checkpoint (a directory holding
/// model.safetensors and config.json, such as data/checkpoint).
#[pyclass(frozen, module = "drivescript")]
struct Sampler {
    trained: drivescript::train::Trained,
}

#[pymethods]
impl Sampler {
    /// Loads the checkpoint in `checkpoint_dir`.
    #[new]
    fn new(py: Python<'_>, checkpoint_dir: PathArg) -> PyResult<Self> {
        let checkpoint_dir = checkpoint_dir.0;
        no_nul(&checkpoint_dir, "checkpoint_dir")?;
        detached(py, "checkpoint reader", || {
            drivescript::train::load(&checkpoint_dir)
                .map(|trained| Self { trained })
                .map_err(|e| {
                    // A directory that is not there is an OSError, as for Scene.load (the
                    // README promises one), not a ValueError like a malformed checkpoint.
                    let absent = matches!(e, drivescript::train::TrainError::Io { .. })
                        && std::fs::metadata(&checkpoint_dir)
                            .is_err_and(|m| m.kind() == std::io::ErrorKind::NotFound);
                    if absent {
                        PyFileNotFoundError::new_err(e.to_string())
                    } else {
                        PyValueError::new_err(e.to_string())
                    }
                })
        })
    }

    /// Future steps the model generates.
    #[getter]
    fn horizon(&self) -> usize {
        self.trained.meta.config.window.future
    }

    /// Samples futures of `scene` guided by `scripts`, as `drivescript simulate` does (same
    /// settings and defaults, guidance in output space, save `samples`: 4 here, 1 there; the scripts are compiled and validated on the scene cut to the
    /// sampled horizon first). Returns float64 `[samples, agents, steps, 3]`, NaN where an
    /// agent is absent; `steps` is `horizon` or the model's.
    ///
    /// `task` is "conditional" (history and recorded end points known) or "unconditional"
    /// (history only: what behaviour scripts such as cut_in are tuned for). Ctrl-C stops it
    /// within one denoising step (KeyboardInterrupt). `guidance` left out is the strength
    /// chosen for the checkpoint, as `simulate --lambda` left out.
    #[pyo3(signature = (scene, scripts = Vec::new(), samples = Arg::Default(4), *,
        seed = Arg::Default(1), steps = Arg::Default(32), task = Text::Default("conditional"),
        horizon = None,
        guidance = Arg::Default(sampler::BEHAVIOUR_LAMBDA),
        realism = Arg::Default(sampler::REALISM_WEIGHT),
        polish = Arg::Default(sampler::POLISH_STEPS)))]
    #[allow(clippy::too_many_arguments)]
    fn sample<'py>(
        &self,
        py: Python<'py>,
        scene: &Scene,
        scripts: Vec<PyRef<'py, CostScript>>,
        samples: Arg<usize>,
        seed: Arg<u64>,
        steps: Arg<usize>,
        task: Text,
        horizon: Option<Arg<usize>>,
        guidance: Arg<f64>,
        realism: Arg<f64>,
        polish: Arg<usize>,
    ) -> PyResult<Bound<'py, PyAny>> {
        let (samples, seed, steps) = (
            samples.get(py, "samples")?,
            seed.get(py, "seed")?,
            steps.get(py, "steps")?,
        );
        let horizon = opt(py, &horizon, "horizon")?;
        let guidance_given = matches!(guidance, Arg::Given(_));
        let (guidance, realism, polish) = (
            // Not given: the strength chosen for the checkpoint, as `simulate` takes it.
            if guidance_given {
                guidance.get(py, "guidance")?
            } else {
                self.trained.meta.behaviour_lambda()
            },
            realism.get(py, "realism")?,
            polish.get(py, "polish")?,
        );
        // As `simulate --lambda` without a script: a weight with nothing to weigh was
        // dropped without a word (0, unguided, says nothing wrong).
        // (One out of range is the sampler's settings error, below.)
        if guidance_given && guidance > 0.0 && guidance <= sampler::MAX_WEIGHT && scripts.is_empty()
        {
            return Err(PyValueError::new_err(format!(
                "guidance = {}: no script to weigh; give scripts (or leave guidance out)",
                drivescript::geom::num(guidance)
            )));
        }
        // As `simulate --script F --script F`: a script given twice weighed twice as much,
        // without a word.
        for (i, s) in scripts.iter().enumerate() {
            if let Some(j) = scripts[..i]
                .iter()
                .position(|t| t.spec.source == s.spec.source && t.spec.params == s.spec.params)
            {
                return Err(PyValueError::new_err(format!(
                    "scripts[{i}] is scripts[{j}] again ({}, the same source and parameters): \
                     each script counts once; to weigh it more, raise guidance",
                    drivescript::io::name::shown(&s.spec.name)
                )));
            }
        }
        let task = match task.get(py, "task")?.as_str() {
            "conditional" => sampler::Task::Conditional,
            "unconditional" => sampler::Task::Unconditional,
            other => {
                return Err(PyValueError::new_err(format!(
                    "task = {other:?}: \"conditional\" or \"unconditional\""
                )))
            }
        };
        // `drivescript simulate`'s settings, its defaults where Python gives none.
        let cfg = SampleConfig {
            steps,
            samples,
            seed,
            lambda: guidance,
            task,
            // Where guidance acts, as `simulate` takes it by default: the denoiser, which
            // `simulate` left for output space (one setting, one default), gave other samples
            // than the CLI for the same seed and settings, without a word.
            guidance: sampler::DEFAULT_GUIDANCE,
            known_weight: 1.0,
            schedule: sampler::LambdaSchedule::Fading,
            clamp: sampler::Clamp::Coordinate,
            realism: drivescript::cost::Realism {
                weight: realism,
                ..Default::default()
            },
            polish,
            horizon,
            script_budget: drivescript::sample::DEFAULT_SCRIPT_BUDGET,
        };
        let spec = AttemptSpec {
            scripts: scripts.iter().map(|s| s.spec.clone()).collect(),
            checks: Vec::new(),
            cfg,
            replan: None,
            refuse_dead_terms: false,
        };
        let raw = scene.inner.clone();
        let done = detached_interruptible(py, "sampler", |stop| {
            Ok(sampler::attempt_until(&self.trained, &raw, &spec, stop))
        })?;
        let done = done.map_err(|e| match e {
            AttemptError::Script(e) => script_error(py, &e),
            AttemptError::Sample(sampler::SampleError::Cost(e)) => script_error(py, &e),
            // The sampler names its setting `lambda`, which Python calls `guidance`: the
            // message named a keyword the caller never passed.
            AttemptError::Sample(sampler::SampleError::Settings(m)) if m.starts_with("lambda ") => {
                PyValueError::new_err(format!("sampler settings: guidance: {m}"))
            }
            AttemptError::Sample(sampler::SampleError::Settings(m)) => {
                PyValueError::new_err(format!("sampler settings: {m}"))
            }
            other => PyRuntimeError::new_err(other.to_string()),
        })?;
        let c = scene.inner.meta.current_step;
        let agents = scene.inner.agents.len();
        let n = done
            .samples
            .first()
            .map_or(0, |s| s.scene.num_steps() - c - 1);
        let mut out = Vec::with_capacity(done.samples.len() * agents * n * 3);
        for s in &done.samples {
            out.extend(Trajectories::recorded(&s.scene).to_array());
        }
        let a = Array4::from_shape_vec((done.samples.len(), agents, n, 3), out)
            .map_err(|e| PyRuntimeError::new_err(e.to_string()))?;
        Ok(a.into_pyarray(py).into_any())
    }
}

/// A behaviour checker's verdict on a trajectory: the independent judge that `simulate
/// --auto`, `eval` and `ask` use.
#[pyclass(frozen, module = "drivescript")]
struct Verdict {
    /// Whether the behaviour happened plausibly (the headline).
    #[pyo3(get)]
    passed: bool,
    /// Whether its geometric condition alone holds.
    #[pyo3(get)]
    achieved: bool,
    /// Implausible motion or collisions of the agents it names, in words.
    #[pyo3(get)]
    violations: Vec<String>,
    /// The quantities behind the verdict, by name.
    #[pyo3(get)]
    measured: std::collections::BTreeMap<String, f64>,
    /// Why, in words.
    #[pyo3(get)]
    reason: String,
    /// The ids of the agents the behaviour names.
    #[pyo3(get)]
    named: Vec<i64>,
}

#[pymethods]
impl Verdict {
    fn __repr__(&self) -> String {
        format!(
            "Verdict(passed={}, reason={:?})",
            if self.passed { "True" } else { "False" },
            self.reason
        )
    }
}

fn behaviour(name: &str) -> PyResult<Behavior> {
    Behavior::from_name(name).ok_or_else(|| {
        PyValueError::new_err(format!(
            "unknown behaviour {name:?}; one of {}",
            behaviors::ALL.map(|b| b.name()).join(", ")
        ))
    })
}

/// Judges whether `behaviour` (e.g. "cut_in") happened in `scene` with its future replaced
/// by `traj` (float64 `[agents, steps, 3]`, NaN where unobserved), with the agents in their
/// roles given by `params` (e.g. {"cutter": 401, "victim": 405}; see `suggest`).
#[pyfunction]
#[pyo3(signature = (behaviour, scene, traj, params = None))]
fn check(
    py: Python<'_>,
    behaviour: Text,
    scene: &Scene,
    traj: Bound<'_, PyAny>,
    params: Option<&Bound<'_, PyDict>>,
) -> PyResult<Verdict> {
    let b = self::behaviour(&behaviour.get(py, "behaviour")?)?;
    let params = params_from(params)?;
    // As `eval --param`: a name the checker does not read (`gapp`) was dropped without a word
    // and the verdict taken for its default.
    b.check_param_names(&params)
        .map_err(|e| PyValueError::new_err(e.to_string()))?;
    let (_, mut t) = trajectories(scene, &traj, false)?;
    let t = t.remove(0);
    let inner = scene.inner.clone();
    let v = detached(py, "checker", move || {
        let judged = t.applied_to(&inner).map_err(PyValueError::new_err)?;
        behaviors::check(b, &judged, &params).map_err(|e| PyValueError::new_err(e.to_string()))
    })?;
    Ok(Verdict {
        passed: v.passed,
        achieved: v.achieved,
        violations: v.violations,
        measured: v.measured,
        reason: v.reason,
        named: v.named,
    })
}

/// Agents of `scene` suited to `behaviour` over `steps` future steps (default: the recorded
/// future), as `simulate --auto` chooses them: the parameters for its script and checker, or
/// None when no agents suit.
#[pyfunction]
#[pyo3(signature = (behaviour, scene, steps = None))]
fn suggest<'py>(
    py: Python<'py>,
    behaviour: Text,
    scene: &Scene,
    steps: Option<Arg<usize>>,
) -> PyResult<Option<Bound<'py, PyDict>>> {
    let steps = opt(py, &steps, "steps")?;
    let b = self::behaviour(&behaviour.get(py, "behaviour")?)?;
    // The horizon checked as `log_future` checks it: 0 steps suggested agents for a
    // behaviour that has no time to happen.
    let steps = scene.horizon(steps)?;
    let inner = scene.inner.clone();
    let p = detached(py, "behaviour suggestion", move || {
        Ok(drivescript::eval::suggest::suggest(
            b,
            &inner.with_horizon(steps),
            steps,
        ))
    })?;
    p.map(|p| params_to(py, &p)).transpose()
}

/// The behaviours the checkers know, by name.
#[pyfunction]
fn behaviours() -> Vec<&'static str> {
    behaviors::ALL.map(|b| b.name()).to_vec()
}

/// The default resource limits of a cost script, name -> value (wall time in seconds).
#[pyfunction]
fn limits<'py>(py: Python<'py>) -> PyResult<Bound<'py, PyDict>> {
    let l = Limits::default();
    let d = PyDict::new(py);
    d.set_item("max_operations", l.max_operations)?;
    d.set_item("max_call_levels", l.max_call_levels)?;
    d.set_item("max_expr_depth", l.max_expr_depth)?;
    d.set_item("max_string_size", l.max_string_size)?;
    d.set_item("max_array_size", l.max_array_size)?;
    d.set_item("max_variables", l.max_variables)?;
    d.set_item("wall_time", l.wall_time.as_secs_f64())?;
    d.set_item("max_source_bytes", l.max_source_bytes)?;
    d.set_item("max_series_bytes", l.max_series_bytes)?;
    d.set_item("max_memory_growth", l.max_memory_growth)?;
    Ok(d)
}

/// The compiled half of the `drivescript` package.
#[pymodule]
fn _native(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("ScriptError", m.py().get_type::<ScriptError>())?;
    m.add_class::<Scene>()?;
    m.add_class::<CostScript>()?;
    m.add_class::<CostResult>()?;
    m.add_class::<Sampler>()?;
    m.add_class::<Verdict>()?;
    m.add_function(wrap_pyfunction!(check, m)?)?;
    m.add_function(wrap_pyfunction!(suggest, m)?)?;
    m.add_function(wrap_pyfunction!(behaviours, m)?)?;
    m.add_function(wrap_pyfunction!(limits, m)?)?;
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    Ok(())
}
