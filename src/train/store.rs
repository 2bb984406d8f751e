//! Where training windows come from: a scene list held in memory (tests, small corpora), or a
//! window store on disk that a corpus of any size is streamed into once, one scene at a time,
//! and read back a batch at a time, so that memory stays flat as the corpus grows.

use std::collections::BTreeMap;
use std::fs::File;
use std::io::{BufWriter, Write};
use std::path::{Path, PathBuf};

use super::dataset::{windows, Window, WindowConfig, AGENT_ATTRS};
use super::rng::Rng;
use super::trainer::{is_validation, TrainError};
use crate::scene::{AgentType, Scene};

/// How many complete futures are kept for fitting the PCA basis (a uniform sample of all of
/// them): enough for a basis of a few dozen components, and bounded whatever the corpus.
pub const PCA_SAMPLE: usize = 20_000;

/// A corpus of training and validation windows.
pub trait WindowSource {
    /// Number of training windows.
    fn train_len(&self) -> usize;
    /// Number of validation windows.
    fn val_len(&self) -> usize;
    /// Training window `i`.
    fn train_window(&self, i: usize) -> Result<Window, TrainError>;
    /// Validation window `i`.
    fn val_window(&self, i: usize) -> Result<Window, TrainError>;
    /// Which scenes were cut, and what the training windows hold.
    fn summary(&self) -> &Summary;
    /// Complete residual futures of the training windows' moving agents (all of them, or a
    /// uniform sample of at most [`PCA_SAMPLE`]): what the PCA basis is fitted on.
    fn futures(&self) -> &[Vec<f64>] {
        &self.summary().tally.futures
    }
    /// Ids of the scenes that gave training windows.
    fn train_scenes(&self) -> Vec<String> {
        self.summary().train_ids.clone()
    }
    /// Ids of the scenes that gave validation windows.
    fn val_scenes(&self) -> Vec<String> {
        self.summary().val_ids.clone()
    }
    /// Agents with a future to learn from in the training windows, per type.
    fn type_counts(&self) -> BTreeMap<AgentType, usize> {
        self.summary().tally.types.clone()
    }
    /// Warnings naming the scenarios read from the corpora more than once, whose windows
    /// were each cut once per copy; none where each was read once.
    fn repeated_scenarios(&self) -> Vec<String> {
        self.summary().copies.warnings()
    }
}

/// What every [`WindowSource`] knows besides its windows: the scenes on each side of the
/// split, and the training windows' futures and agent types.
pub struct Summary {
    train_ids: Vec<String>,
    val_ids: Vec<String>,
    tally: Tally,
    copies: crate::io::copies::ScenarioCopies,
}

impl Summary {
    fn new() -> Self {
        Self {
            train_ids: Vec::new(),
            val_ids: Vec::new(),
            tally: Tally::new(),
            copies: crate::io::copies::ScenarioCopies::new(),
        }
    }
}

/// How a corpus is split into training and validation.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SplitBy {
    /// By scene id ([`is_validation`]): for recordings of a few long roads (NGSIM), where a
    /// place held out whole would leave too little.
    Scene,
    /// By town or city ([`town`]): every scene of a place trains or every one validates, so
    /// that validation measures places the model never saw.
    Town,
}

/// The place a CommonRoad-style scene id names: `DEU_Flensburg-10_1_T-1` → `DEU_Flensburg`
/// (the part before the first `-`; the whole id where there is none).
pub fn town(scenario_id: &str) -> &str {
    scenario_id.split('-').next().unwrap_or(scenario_id)
}

/// Which scenes validate: those of fold `fold` ([`is_validation`] of the scene id or of its
/// town, as each corpus is split), and in corpora split by town those of `towns` as well.
#[derive(Debug, Clone, Default)]
pub struct Holdout {
    /// The fold.
    pub fold: u64,
    /// Towns held out besides the fold's.
    pub towns: Vec<String>,
}

impl Holdout {
    /// Whether `scenario_id` validates under `split`.
    pub fn validates(&self, scenario_id: &str, split: SplitBy) -> bool {
        match split {
            SplitBy::Scene => is_validation(scenario_id, self.fold),
            SplitBy::Town => {
                let t = town(scenario_id);
                is_validation(t, self.fold) || self.towns.iter().any(|x| x == t)
            }
        }
    }
}

/// Complete futures and agent types of windows, and a uniform sample of at most
/// [`PCA_SAMPLE`] futures (reservoir sampling with a fixed seed: the same corpus gives the
/// same sample).
struct Tally {
    futures: Vec<Vec<f64>>,
    seen: usize,
    rng: Rng,
    types: BTreeMap<AgentType, usize>,
}

impl Tally {
    fn new() -> Self {
        Self {
            futures: Vec::new(),
            seen: 0,
            rng: Rng::new(0x5EED_F00D),
            types: BTreeMap::new(),
        }
    }

    fn add(&mut self, w: &Window, cfg: &WindowConfig) {
        for f in w.residual_futures(cfg) {
            self.seen += 1;
            if self.futures.len() < PCA_SAMPLE {
                self.futures.push(f);
            } else {
                let j = self.rng.below(self.seen);
                if j < PCA_SAMPLE {
                    self.futures[j] = f;
                }
            }
        }
        for k in 0..w.agents.len() {
            if w.is_mover_slot(k) && w.agent_future_seen(cfg, k).is_some() {
                let a = &w.attrs[k];
                let t = if a[0] > 0.0 {
                    AgentType::Vehicle
                } else if a[1] > 0.0 {
                    AgentType::Cyclist
                } else {
                    AgentType::Pedestrian
                };
                *self.types.entry(t).or_default() += 1;
            }
        }
    }
}

/// Windows cut from scenes in memory, split by scene id.
pub struct SceneWindows {
    train: Vec<Window>,
    val: Vec<Window>,
    summary: Summary,
}

impl SceneWindows {
    /// Cuts the windows of `scenes`; the scenes of fold `fold` validate ([`is_validation`]).
    pub fn new(scenes: &[Scene], cfg: &WindowConfig, fold: u64) -> Self {
        let mut out = Self {
            train: Vec::new(),
            val: Vec::new(),
            summary: Summary::new(),
        };
        for s in scenes {
            let w = windows(s, cfg);
            if w.is_empty() {
                continue;
            }
            let id = s.meta.scenario_id.clone();
            if is_validation(&id, fold) {
                out.summary.val_ids.push(id);
                out.val.extend(w);
            } else {
                out.summary.train_ids.push(id);
                for x in &w {
                    out.summary.tally.add(x, cfg);
                }
                out.train.extend(w);
            }
        }
        out
    }
}

impl WindowSource for SceneWindows {
    fn train_len(&self) -> usize {
        self.train.len()
    }
    fn val_len(&self) -> usize {
        self.val.len()
    }
    fn train_window(&self, i: usize) -> Result<Window, TrainError> {
        Ok(self.train[i].clone())
    }
    fn val_window(&self, i: usize) -> Result<Window, TrainError> {
        Ok(self.val[i].clone())
    }
    fn summary(&self) -> &Summary {
        &self.summary
    }
}

/// First bytes of a window file.
const MAGIC: &[u8; 8] = b"DSWIN01\n";

/// Training and validation windows in two files of a cache directory, read back one window at
/// a time: memory holds the offsets and the PCA sample, not the windows.
pub struct WindowStore {
    cfg: WindowConfig,
    train: Part,
    val: Part,
    summary: Summary,
}

/// One file of windows and where each starts.
struct Part {
    path: PathBuf,
    file: File,
    offsets: Vec<u64>,
}

impl Part {
    fn get(&self, i: usize, cfg: &WindowConfig) -> Result<Window, TrainError> {
        let start = self.offsets[i];
        let end = self.offsets[i + 1];
        let mut buf = vec![0u8; (end - start) as usize];
        read_at(&self.file, &mut buf, start).map_err(|e| io_err(&self.path, e.to_string()))?;
        decode(&buf, cfg).map_err(|m| io_err(&self.path, format!("window {i}: {m}")))
    }
}

#[cfg(unix)]
fn read_at(f: &File, buf: &mut [u8], off: u64) -> std::io::Result<()> {
    use std::os::unix::fs::FileExt;
    f.read_exact_at(buf, off)
}

#[cfg(not(unix))]
fn read_at(f: &File, buf: &mut [u8], off: u64) -> std::io::Result<()> {
    use std::io::{Read, Seek, SeekFrom};
    let mut f = f;
    f.seek(SeekFrom::Start(off))?;
    f.read_exact(buf)
}

fn io_err(path: &Path, message: String) -> TrainError {
    TrainError::Io {
        path: path.display().to_string(),
        message,
    }
}

/// One source of scenes and how it is split.
#[derive(Debug, Clone)]
pub struct Corpus {
    /// Scene files or directories.
    pub path: PathBuf,
    /// How its scenes are held out.
    pub split: SplitBy,
}

/// The window files of a cache directory.
const CACHE_FILES: [&str; 2] = ["train.windows", "val.windows"];

/// Whether `name` is one of the files [`WindowStore::build`] writes into its directory: a
/// window file, or the temporary copy of one that a run stopped while building left behind
/// (`train.windows.tmp-PID`).
fn is_cache_file(name: &str) -> bool {
    CACHE_FILES.iter().any(|f| {
        name == *f
            || name
                .strip_prefix(f)
                .and_then(|rest| rest.strip_prefix(".tmp-"))
                .is_some_and(|pid| !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit()))
    })
}

/// `path` made absolute with its links resolved, as far as it exists: a directory not yet
/// created is its nearest existing ancestor's canonical path joined with the rest, whose
/// `..` are taken lexically (nothing there yet can be a link).
fn resolved(path: &Path) -> Option<PathBuf> {
    let mut rest = Vec::new();
    let mut p = path;
    loop {
        if let Ok(mut out) = std::fs::canonicalize(p) {
            for c in rest.iter().rev() {
                match c {
                    std::path::Component::ParentDir => {
                        out.pop();
                    }
                    std::path::Component::Normal(n) => out.push(n),
                    _ => {}
                }
            }
            return Some(out);
        }
        if p == Path::new(".") {
            // The working directory itself is gone.
            return None;
        }
        rest.push(p.components().next_back()?);
        p = p
            .parent()
            .filter(|q| !q.as_os_str().is_empty())
            .unwrap_or(Path::new("."));
    }
}

/// Why `dir`, an output directory, may not be written: it is, or is inside, an input
/// directory of `corpora` (its files would go among the scenes they are made from, and a later
/// run over that directory would read them as scenes). `None` where it lies apart from them.
fn among_inputs(dir: &Path, corpora: &[Corpus]) -> Option<String> {
    let d = resolved(dir)?;
    corpora.iter().find_map(|c| {
        let input = std::fs::canonicalize(&c.path).ok()?;
        (input.is_dir() && d.starts_with(&input)).then(|| {
            format!(
                "{} the input directory {}: training writes its outputs apart from its inputs; \
                 choose a directory outside it",
                if d == input { "is" } else { "is inside" },
                c.path.display()
            )
        })
    })
}

/// What every output directory of training is checked for first: that it lies apart from the
/// inputs ([`among_inputs`]) and, where something is there, that it is a directory (`not_dir`
/// says what to name instead). `what` names it in the message ("the checkpoint directory
/// (--out)"). Whether the directory exists.
fn apart_from_inputs(
    dir: &Path,
    corpora: &[Corpus],
    what: &str,
    not_dir: &str,
) -> Result<bool, TrainError> {
    let why = match among_inputs(dir, corpora) {
        Some(why) => why,
        None => match std::fs::metadata(dir) {
            Ok(m) if !m.is_dir() => format!("is not a directory{not_dir}"),
            Ok(_) => return Ok(true),
            Err(_) => return Ok(false),
        },
    };
    Err(refusal(dir, what, why))
}

/// The error refusing output directory `dir`, named by `what`, for `why`.
fn refusal(dir: &Path, what: &str, why: String) -> TrainError {
    TrainError::Data(format!("{}: {what} {why}", dir.display()))
}

/// [`check_out_dir`] for `train --export DIR`, said of `--export`: the checkpoint's checks
/// named `--out`, a flag the command was not given (`train --export data/x` was told "the
/// checkpoint directory (--out) is inside the input directory data"). What the export may
/// replace it checks itself: nothing (`train::export` writes into a new or empty directory).
pub fn check_export_dir(dir: &Path, corpora: &[Corpus]) -> Result<(), TrainError> {
    let exists = apart_from_inputs(
        dir,
        corpora,
        "the export directory (--export)",
        ": name a new or empty directory",
    )?;
    // Said before the windows are cut, as `train::export` would say it after (a large corpus
    // was read and cut first, minutes of work, and then refused).
    if exists
        && std::fs::read_dir(dir)
            .map_err(|e| io_err(dir, e.to_string()))?
            .next()
            .is_some()
    {
        return Err(io_err(
            dir,
            "is not empty: export into a new or empty directory (nothing in it is replaced)".into(),
        ));
    }
    Ok(())
}

/// Refuses a window cache (`train --cache`) that is the export directory (`train --export`),
/// or lies inside it or around it: the windows were cut into it (the whole corpus read first),
/// and the export then refused the directory as "not empty", leaving the cache there; an
/// export inside the cache is a directory the cache refuses at its next start.
pub fn check_cache_apart_from_export(cache: &Path, export: &Path) -> Result<(), TrainError> {
    let (Some(c), Some(e)) = (resolved(cache), resolved(export)) else {
        return Ok(());
    };
    let why = if c == e {
        "is the export directory (--export)"
    } else if c.starts_with(&e) {
        "is inside the export directory (--export)"
    } else if e.starts_with(&c) {
        "holds the export directory (--export)"
    } else {
        return Ok(());
    };
    Err(refusal(
        cache,
        "the window cache (--cache)",
        format!(
            "{why} {}: the export directory holds the export's files alone; give the cache a \
             directory apart from it (or leave --cache out for a temporary one)",
            export.display()
        ),
    ))
}

/// Refuses a checkpoint directory (`train --out`) that is, or is inside, a directory of
/// `corpora`: the checkpoint's files would go among the scenes it is trained on, the same
/// mistake [`check_cache_dir`] refuses for the window cache. Also refused: a path that is not
/// a directory (a file, `/dev/null`: it said "OUT/windows: Not a directory"), and a directory
/// whose `config.json` is not a checkpoint's (training replaced the user's file with its own),
/// or that holds a file training writes (weights, optimiser state) without any `config.json`:
/// every checkpoint has one, so those files are the user's. Checked before any data is read.
pub fn check_out_dir(dir: &Path, corpora: &[Corpus]) -> Result<(), TrainError> {
    const WHAT: &str = "the checkpoint directory (--out)";
    let refuse = |why: String| Err(refusal(dir, WHAT, why));
    if !apart_from_inputs(
        dir,
        corpora,
        WHAT,
        ": name a new directory, or an earlier run's checkpoint",
    )? {
        return Ok(());
    }
    let config = dir.join("config.json");
    if std::fs::symlink_metadata(&config).is_err() {
        let written = [
            "model.safetensors",
            crate::train::trainer::ONLINE_FILE,
            crate::train::trainer::OPTIMIZER_FILE,
        ];
        if let Some(f) = written
            .iter()
            .map(|f| dir.join(f))
            .find(|f| std::fs::symlink_metadata(f).is_ok())
        {
            return refuse(format!(
                "holds {} but no config.json, so it is no checkpoint of drivescript's: training \
                 would replace that file; move it, or choose another --out",
                f.display()
            ));
        }
        // Another run's window cache (`--cache DIR`): the checkpoint's files were written
        // among its windows, and that run's next start refused its cache as holding files
        // not its own.
        if let Some(f) = CACHE_FILES
            .iter()
            .map(|f| dir.join(f))
            .find(|f| std::fs::symlink_metadata(f).is_ok())
        {
            return refuse(format!(
                "holds {} but no config.json: it is a window cache (--cache), which holds its \
                 own files alone; choose another --out",
                f.display()
            ));
        }
    } else {
        // Why it is not, where it cannot be read as JSON: a checkpoint's own config damaged
        // (a NaN written into it by hand) was called "not a checkpoint's config" with no
        // more, as if it were a file of the user's that happened to be there.
        let read = crate::io::read_regular_text(
            &config,
            crate::train::trainer::MAX_CONFIG_BYTES,
            "checkpoint config",
        )
        .map_err(|e| e.reason())
        .and_then(|t| {
            serde_json::from_str::<serde_json::Value>(&t).map_err(|e| {
                format!(
                    "line {}, column {}: {}",
                    e.line(),
                    e.column(),
                    crate::io::without_position(&e.to_string(), e.line(), e.column())
                )
            })
        });
        let why = match read {
            Ok(v) if v.get("version").is_some() && v.get("config").is_some() => None,
            Ok(_) => Some(String::new()),
            Err(e) => Some(format!(" ({e})")),
        };
        if let Some(why) = why {
            return refuse(format!(
                "holds {}, which is not a checkpoint's config{why}: training would replace it; \
                 move it, or choose another --out",
                config.display()
            ));
        }
    }
    Ok(())
}

/// Refuses a run that would replace the checkpoint already in `out` (`train --out`) with
/// another run's, unless `force`: a new run (no `resume`), or one resuming a checkpoint in
/// another directory. Only resuming `out` itself continues the checkpoint that is there.
/// `train --resume A --out B`, where B held a checkpoint of its own, replaced B's weights,
/// config and optimiser state with A's continuation without a word.
pub fn check_replaces_checkpoint(
    out: &Path,
    resume: Option<&Path>,
    force: bool,
) -> Result<(), TrainError> {
    if force || std::fs::symlink_metadata(out.join("model.safetensors")).is_err() {
        return Ok(());
    }
    let same = |a: &Path, b: &Path| match (a.canonicalize(), b.canonicalize()) {
        (Ok(a), Ok(b)) => a == b,
        _ => a == b,
    };
    match resume {
        Some(from) if same(from, out) => Ok(()),
        Some(from) => Err(TrainError::Data(format!(
            "{}: the checkpoint directory (--out) already holds a checkpoint, and --resume \
             continues another one ({}): training would replace the first with the second's \
             continuation; give --out {} to continue it in place, choose another --out, or pass \
             --force to replace it",
            out.display(),
            from.display(),
            from.display()
        ))),
        None => Err(TrainError::Data(format!(
            "{} already holds a checkpoint: continue it with --resume {}, choose another --out, \
             or pass --force to replace it",
            out.display(),
            out.display()
        ))),
    }
}

/// Refuses a window cache (`train --cache`) at the path of a file the checkpoint in `out` is
/// written as: `--cache OUT/model.safetensors` made that a directory of windows, trained, and
/// only then failed to save the checkpoint ("Is a directory"), the run's work lost.
///
/// Also refused: a cache that is the checkpoint directory itself, or holds it. The run
/// trained, and the checkpoint's files lay among the windows, so the next start (a resume
/// with the same flags) refused the cache as holding files not its own.
pub fn check_cache_beside_checkpoint(cache: &Path, out: &Path) -> Result<(), TrainError> {
    if let (Some(c), Some(o)) = (resolved(cache), resolved(out)) {
        if o.starts_with(&c) {
            return Err(refusal(
                cache,
                "the window cache (--cache)",
                format!(
                    "{} the checkpoint directory (--out) {}: the cache holds its own files \
                     alone, and its next start would refuse the checkpoint's; give the cache \
                     another directory (the default is OUT/windows)",
                    if o == c { "is" } else { "holds" },
                    out.display()
                ),
            ));
        }
    }
    let resolved = |p: &Path| {
        p.canonicalize()
            .or_else(|_| std::path::absolute(p))
            .unwrap_or_else(|_| p.to_path_buf())
    };
    let Some(name) = cache.file_name().and_then(|n| n.to_str()) else {
        return Ok(());
    };
    let files = [
        "config.json",
        "model.safetensors",
        crate::train::trainer::ONLINE_FILE,
        crate::train::trainer::OPTIMIZER_FILE,
    ];
    let parent = match cache.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    if files.contains(&name) && resolved(parent) == resolved(out) {
        return Err(refusal(
            cache,
            "the window cache (--cache)",
            format!(
                "is where the checkpoint in {} writes its {name}: give the cache another \
                 name (the default is OUT/windows)",
                out.display()
            ),
        ));
    }
    Ok(())
}

/// An exclusive hold on a checkpoint directory (`train --out`) for the life of a run
/// ([`lock_out_dir`]), released when dropped or when the process ends however it ends.
/// Dropped, it also removes the directories [`lock_out_dir`] made that are still empty: a run
/// refused after the lock (a held-out town no scene is in, a scene of another time step) left
/// an empty `--out` behind.
#[derive(Debug)]
pub struct OutLock {
    _dir: File,
    /// The directories made for the lock, deepest first.
    made: Vec<PathBuf>,
}

impl Drop for OutLock {
    fn drop(&mut self) {
        // `remove_dir` removes only an empty directory: a checkpoint written, or anything
        // another put there, keeps it.
        for d in &self.made {
            if std::fs::remove_dir(d).is_err() {
                break;
            }
        }
    }
}

/// The directories that making `dir` would create (it and its missing parents), deepest
/// first.
fn missing_dirs(dir: &Path) -> Vec<PathBuf> {
    dir.ancestors()
        .filter(|a| !a.as_os_str().is_empty())
        .take_while(|a| std::fs::symlink_metadata(a).is_err())
        .map(Path::to_path_buf)
        .collect()
}

/// Removes the directories of `made` (deepest first) that are empty: what a refused build made.
fn remove_made_dirs(made: &[PathBuf]) {
    for d in made {
        if std::fs::remove_dir(d).is_err() {
            break;
        }
    }
}

/// Makes the checkpoint directory `dir` (`train --out`) and takes it for this run: an advisory
/// `flock` on the directory itself, so that no file is added to it and a killed run leaves no
/// stale lock. Two runs started into one `--out` both trained, rewrote each other's window
/// cache and replaced each other's checkpoint files in turn (a `config.json` of one run beside
/// the weights of the other), without a word; the second is now refused.
pub fn lock_out_dir(dir: &Path) -> Result<OutLock, TrainError> {
    let made = missing_dirs(dir);
    crate::io::create_output_dir(dir).map_err(|e| TrainError::Data(e.to_string()))?;
    let file = File::open(dir).map_err(|e| {
        remove_made_dirs(&made);
        io_err(dir, format!("cannot open it: {e}"))
    })?;
    #[cfg(unix)]
    {
        use std::os::unix::io::AsRawFd;
        // SAFETY: flock on a descriptor this function owns; no memory is involved.
        let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if rc != 0 {
            let e = std::io::Error::last_os_error();
            // Made here, the directory could not be another's yet: nothing to remove.
            return Err(if e.kind() == std::io::ErrorKind::WouldBlock {
                TrainError::Data(format!(
                    "{}: another drivescript train is writing its checkpoint there (--out): \
                     wait for it to end, or choose another --out",
                    dir.display()
                ))
            } else {
                io_err(dir, format!("cannot lock it: {e}"))
            });
        }
    }
    Ok(OutLock { _dir: file, made })
}

/// Refuses a cache directory that is, or is inside, a directory of `corpora` (the windows
/// would go among the scenes they are cut from), and one holding anything besides the
/// cache's own files: building replaces its files at every start, so a directory of the
/// user's (or a checkpoint's) is no cache to write into. An earlier run's cache is reused.
pub fn check_cache_dir(dir: &Path, corpora: &[Corpus]) -> Result<(), TrainError> {
    const WHAT: &str = "the window cache (--cache, default OUT/windows)";
    let cache_err = |message: String| Err(refusal(dir, WHAT, message));
    if !apart_from_inputs(dir, corpora, WHAT, "")? {
        return Ok(());
    }
    let entries = std::fs::read_dir(dir).map_err(|e| io_err(dir, e.to_string()))?;
    for e in entries {
        let e = e.map_err(|e| io_err(dir, e.to_string()))?;
        let name = e.file_name();
        let ours =
            name.to_str().is_some_and(is_cache_file) && e.file_type().is_ok_and(|t| t.is_file());
        if !ours {
            return cache_err(format!(
                "holds {}, which is not one of its files ({}): the cache's files are replaced \
                 at every start, so it must be a new or empty directory, or an earlier run's \
                 cache",
                e.path().display(),
                CACHE_FILES.join(", ")
            ));
        }
    }
    Ok(())
}

/// A new, empty directory in the system's temporary directory for a run's scratch window
/// cache (`train --export` without `--cache`), made here so that it is this run's own: the
/// fixed name `drivescript-export-PID` took over a directory of that name already there (left
/// by another user, or by an earlier process of the same id), built windows into it and then
/// removed it whole. Its name starts with `prefix`.
pub fn scratch_dir(prefix: &str) -> Result<PathBuf, TrainError> {
    let base = std::env::temp_dir();
    let pid = std::process::id();
    for k in 0..1000 {
        let dir = base.join(format!("{prefix}-{pid}-{k}"));
        match std::fs::create_dir(&dir) {
            Ok(()) => return Ok(dir),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => return Err(io_err(&dir, e.to_string())),
        }
    }
    Err(io_err(
        &base,
        format!("holds {prefix}-{pid}-0 to -999 already: no scratch directory could be made"),
    ))
}

/// Removes the windows a build stopped by Ctrl-C or a kill left in the cache `dir`
/// (`train.windows.tmp-PID`, as large as the corpus's windows): every later build, under
/// another PID, added its own beside them. A live process's are its own to finish.
fn remove_dead_temps(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(pid) = name.to_str().filter(|n| is_cache_file(n)).and_then(|n| {
            n.rsplit_once(".tmp-")
                .and_then(|(_, pid)| pid.parse::<u32>().ok())
        }) else {
            continue;
        };
        if pid != std::process::id()
            && !crate::io::process_alive(pid)
            && e.file_type().is_ok_and(|t| t.is_file())
        {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// Most towns an error lists; the rest are counted.
const MAX_TOWNS_SHOWN: usize = 12;

/// Refuses a held-out town (`train --val-town`) that no scene of a corpus split by town is in:
/// it was ignored without a word, and the run validated on the fold alone. The message lists
/// the towns there are.
fn check_towns_found(
    wanted: &[String],
    found: &std::collections::BTreeSet<String>,
) -> Result<(), TrainError> {
    let missing: Vec<&String> = wanted.iter().filter(|t| !found.contains(*t)).collect();
    if missing.is_empty() {
        return Ok(());
    }
    let quoted = |t: &str| format!("\"{}\"", crate::io::name::shown_counted(t));
    let there = if found.is_empty() {
        "no scene is read from a corpus split by town: held-out towns are for --urban \
         corpora"
            .to_string()
    } else {
        let shown: Vec<String> = found
            .iter()
            .take(MAX_TOWNS_SHOWN)
            .map(|t| quoted(t))
            .collect();
        let more = found.len() - shown.len();
        format!(
            "the towns of the --urban scenes are {}{}",
            shown.join(", "),
            if more > 0 {
                format!(" and {more} more")
            } else {
                String::new()
            }
        )
    };
    // At most MAX_TOWNS_SHOWN of them, the rest counted: 3,000 towns given were all repeated,
    // a message of 24 KB.
    let shown_missing: Vec<String> = missing
        .iter()
        .take(MAX_TOWNS_SHOWN)
        .map(|t| quoted(t))
        .collect();
    let more_missing = missing.len() - shown_missing.len();
    Err(TrainError::Data(format!(
        "--val-town {}{}: no scene is in {}; {there} (a town is a scenario id's part before its \
         first `-`)",
        shown_missing.join(" "),
        if more_missing > 0 {
            format!(" and {more_missing} more")
        } else {
            String::new()
        },
        if missing.len() == 1 {
            "that town"
        } else {
            "those towns"
        }
    )))
}

impl WindowStore {
    /// Cuts the windows of every scene of `corpora`, one scene at a time, into `dir`
    /// (`train.windows`, `val.windows`; replaced if present), after [`check_cache_dir`]. The scenes `holdout` names
    /// validate, by scene or by town as each corpus says. `progress(scenes read, windows)` is
    /// called after each scene. Files are read in the order `io::discover` gives, so the same
    /// corpus gives the same windows in the same order (a resumed run draws the same batches).
    pub fn build(
        corpora: &[Corpus],
        cfg: &WindowConfig,
        holdout: &Holdout,
        dir: &Path,
        mut progress: impl FnMut(usize, usize),
    ) -> Result<Self, TrainError> {
        check_cache_dir(dir, corpora)?;
        // A refused build leaves nothing it made: an empty OUT/windows stayed behind.
        let made = missing_dirs(dir);
        std::fs::create_dir_all(dir).map_err(|e| io_err(dir, e.to_string()))?;
        remove_dead_temps(dir);
        // Written under a temporary name and renamed into place at the end: another run
        // training from the same cache keeps reading its open files (the old inodes) instead
        // of finding them truncated under it.
        let open = |name: &str| -> Result<(PathBuf, BufWriter<File>), TrainError> {
            let p = dir.join(format!("{name}.tmp-{}", std::process::id()));
            // Made new, never opened through what lies there: `File::create` followed a link
            // planted at this predictable name and truncated the file it named. Whatever is
            // there (a leftover of a process that had this id, such a link) is removed first;
            // removing a link leaves its target alone.
            match std::fs::symlink_metadata(&p) {
                Ok(m) if m.is_dir() => return Err(io_err(&p, "is a directory: remove it".into())),
                Ok(_) => std::fs::remove_file(&p).map_err(|e| io_err(&p, e.to_string()))?,
                Err(_) => {}
            }
            let f = std::fs::OpenOptions::new()
                .write(true)
                .create_new(true)
                .open(&p)
                .map_err(|e| io_err(&p, e.to_string()))?;
            let mut w = BufWriter::new(f);
            w.write_all(MAGIC).map_err(|e| io_err(&p, e.to_string()))?;
            Ok((p, w))
        };
        let (tp, mut tw) = open("train.windows").inspect_err(|_| remove_made_dirs(&made))?;
        let (vp, mut vw) = match open("val.windows") {
            Ok(v) => v,
            Err(e) => {
                drop(tw);
                let _ = std::fs::remove_file(&tp);
                remove_made_dirs(&made);
                return Err(e);
            }
        };
        let mut toff = vec![MAGIC.len() as u64];
        let mut voff = vec![MAGIC.len() as u64];
        let mut summary = Summary::new();
        let (mut read, mut cut) = (0usize, 0usize);
        let opts = crate::io::LoadOptions::default();
        // The towns of the scenes in corpora split by town, to check `holdout.towns` against.
        let mut towns = std::collections::BTreeSet::new();
        let cutting = (|| -> Result<(), TrainError> {
            for c in corpora {
                let files =
                    crate::io::discover(&c.path).map_err(|e| TrainError::Data(e.to_string()))?;
                // An empty folder was told "no scene is long enough for 51 steps".
                if files.is_empty() {
                    return Err(TrainError::Data(format!(
                        "{}: no scene file in it (supported: {})",
                        crate::io::name::one_line(&c.path.display().to_string()),
                        crate::io::SUPPORTED_FORMATS
                    )));
                }
                for f in files {
                    let scenes = crate::io::load_scenes(&f, &opts)
                        .map_err(|e| TrainError::Data(format!("loading {}: {e}", f.display())))?;
                    for s in scenes {
                        if let Some(m) = super::dataset::step_mismatch(&s) {
                            return Err(TrainError::Data(m));
                        }
                        read += 1;
                        summary.copies.add(&s.meta.scenario_id, &f);
                        if c.split == SplitBy::Town {
                            towns.insert(town(&s.meta.scenario_id).to_string());
                        }
                        let ws = windows(&s, cfg);
                        if ws.is_empty() {
                            progress(read, cut);
                            continue;
                        }
                        let id = s.meta.scenario_id.clone();
                        let val = holdout.validates(&id, c.split);
                        let (path, out, offs) = if val {
                            summary.val_ids.push(id);
                            (&vp, &mut vw, &mut voff)
                        } else {
                            summary.train_ids.push(id);
                            (&tp, &mut tw, &mut toff)
                        };
                        for w in &ws {
                            if !val {
                                summary.tally.add(w, cfg);
                            }
                            let bytes = encode(w, cfg);
                            out.write_all(&bytes)
                                .map_err(|e| io_err(path, e.to_string()))?;
                            offs.push(
                                offs.last().expect("starts with the header") + bytes.len() as u64,
                            );
                            cut += 1;
                        }
                        progress(read, cut);
                    }
                }
            }
            check_towns_found(&holdout.towns, &towns)
        })();
        if let Err(e) = cutting {
            // Half-written windows are no cache: nothing of this run is left in `dir`.
            drop((tw, vw));
            let _ = std::fs::remove_file(&tp);
            let _ = std::fs::remove_file(&vp);
            remove_made_dirs(&made);
            return Err(e);
        }
        let mut done = Vec::new();
        for (p, w, name) in [(tp, tw, "train.windows"), (vp, vw, "val.windows")] {
            w.into_inner()
                .map_err(|e| io_err(&p, e.to_string()))?
                .sync_all()
                .map_err(|e| io_err(&p, e.to_string()))?;
            let dest = dir.join(name);
            std::fs::rename(&p, &dest).map_err(|e| io_err(&dest, e.to_string()))?;
            done.push(dest);
        }
        let vp = done.pop().expect("two files");
        let tp = done.pop().expect("two files");
        let part = |path: PathBuf, offsets: Vec<u64>| -> Result<Part, TrainError> {
            let file = File::open(&path).map_err(|e| io_err(&path, e.to_string()))?;
            Ok(Part {
                path,
                file,
                offsets,
            })
        };
        Ok(Self {
            cfg: *cfg,
            train: part(tp, toff)?,
            val: part(vp, voff)?,
            summary,
        })
    }
}

impl WindowSource for WindowStore {
    fn train_len(&self) -> usize {
        self.train.offsets.len() - 1
    }
    fn val_len(&self) -> usize {
        self.val.offsets.len() - 1
    }
    fn train_window(&self, i: usize) -> Result<Window, TrainError> {
        self.train.get(i, &self.cfg)
    }
    fn val_window(&self, i: usize) -> Result<Window, TrainError> {
        self.val.get(i, &self.cfg)
    }
    fn summary(&self) -> &Summary {
        &self.summary
    }
}

/// A window's bytes: only the agent slots and lanes it holds, little-endian.
fn encode(w: &Window, cfg: &WindowConfig) -> Vec<u8> {
    let steps = cfg.steps();
    let (na, nl, p, m) = (
        w.agents.len(),
        w.lane_ids.len(),
        cfg.lane_points,
        cfg.max_lanes,
    );
    let mut b = Vec::with_capacity(64 + na * steps * 13 + nl * (p * 8 + 8 + nl));
    b.extend((w.scene_id.len() as u32).to_le_bytes());
    b.extend(w.scene_id.as_bytes());
    b.extend((w.current as u64).to_le_bytes());
    for o in w.origin {
        b.extend(o.to_le_bytes());
    }
    b.extend((na as u32).to_le_bytes());
    b.extend((nl as u32).to_le_bytes());
    for (k, &a) in w.agents.iter().enumerate() {
        b.extend((a as u64).to_le_bytes());
        for v in w.attrs[k] {
            b.extend(v.to_le_bytes());
        }
        for t in 0..steps {
            let i = k * steps + t;
            b.push(w.valid[i] as u8);
            for v in w.states[i] {
                b.extend(v.to_le_bytes());
            }
        }
    }
    for (l, id) in w.lane_ids.iter().enumerate() {
        b.extend(id.to_le_bytes());
        for q in &w.lanes[l * p..(l + 1) * p] {
            b.extend(q[0].to_le_bytes());
            b.extend(q[1].to_le_bytes());
        }
        b.extend(&w.lane_conn[l * m..l * m + nl]);
    }
    if cfg.route_frame {
        for k in 0..na {
            let line = w.routes.get(k).map_or(&[][..], |r| &r[..]);
            b.extend((line.len() as u32).to_le_bytes());
            for q in line {
                b.extend(q[0].to_le_bytes());
                b.extend(q[1].to_le_bytes());
            }
        }
    }
    b
}

/// Reads what [`encode`] wrote, checking every count against the configuration.
fn decode(b: &[u8], cfg: &WindowConfig) -> Result<Window, String> {
    let mut r = Reader { b, at: 0 };
    let steps = cfg.steps();
    let (p, m) = (cfg.lane_points, cfg.max_lanes);
    let len = r.u32()? as usize;
    let scene_id = String::from_utf8(r.take(len)?.to_vec()).map_err(|e| e.to_string())?;
    let current = r.u64()? as usize;
    let origin = [r.f64()?, r.f64()?, r.f64()?];
    let na = r.u32()? as usize;
    let nl = r.u32()? as usize;
    if na > cfg.max_agents || nl > m {
        return Err(format!(
            "{na} agents and {nl} lanes, more than the configuration's {} and {m}",
            cfg.max_agents
        ));
    }
    let mut w = Window {
        scene_id,
        current,
        origin,
        agents: Vec::with_capacity(na),
        states: vec![[0f32; 3]; cfg.max_agents * steps],
        valid: vec![false; cfg.max_agents * steps],
        lanes: vec![[0f32; 2]; m * p],
        lane_ids: Vec::with_capacity(nl),
        lane_conn: vec![0u8; m * m],
        attrs: vec![[0f32; AGENT_ATTRS]; cfg.max_agents],
        routes: Vec::new(),
    };
    for k in 0..na {
        w.agents.push(r.u64()? as usize);
        for v in w.attrs[k].iter_mut() {
            *v = r.f32()?;
        }
        for t in 0..steps {
            let i = k * steps + t;
            w.valid[i] = r.take(1)?[0] != 0;
            w.states[i] = [r.f32()?, r.f32()?, r.f32()?];
        }
    }
    for l in 0..nl {
        w.lane_ids.push(r.i64()?);
        for q in &mut w.lanes[l * p..(l + 1) * p] {
            *q = [r.f32()?, r.f32()?];
        }
        w.lane_conn[l * m..l * m + nl].copy_from_slice(r.take(nl)?);
    }
    if cfg.route_frame {
        for k in 0..na {
            let n = r.u32()? as usize;
            // Past the bytes left it is cut short, before anything is allocated for it.
            if n.saturating_mul(8) > b.len() - r.at {
                return Err(format!(
                    "agent slot {k}: a route of {n} points, more than the bytes left"
                ));
            }
            let line: Vec<[f32; 2]> = (0..n)
                .map(|_| Ok([r.f32()?, r.f32()?]))
                .collect::<Result<_, String>>()?;
            let points = line
                .iter()
                .map(|p| crate::geom::Point::new(p[0] as f64, p[1] as f64));
            if n > 0 {
                crate::geom::Polyline::new(points)
                    .map_err(|e| format!("agent slot {k}: route: {e}"))?;
            }
            w.routes.push(line);
        }
    }
    if r.at != b.len() {
        return Err(format!("{} bytes left over", b.len() - r.at));
    }
    Ok(w)
}

struct Reader<'a> {
    b: &'a [u8],
    at: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8], String> {
        let s = self
            .b
            .get(self.at..self.at + n)
            .ok_or_else(|| "cut short".to_string())?;
        self.at += n;
        Ok(s)
    }
    fn arr<const N: usize>(&mut self) -> Result<[u8; N], String> {
        Ok(self.take(N)?.try_into().expect("N bytes"))
    }
    fn u32(&mut self) -> Result<u32, String> {
        Ok(u32::from_le_bytes(self.arr()?))
    }
    fn u64(&mut self) -> Result<u64, String> {
        Ok(u64::from_le_bytes(self.arr()?))
    }
    fn i64(&mut self) -> Result<i64, String> {
        Ok(i64::from_le_bytes(self.arr()?))
    }
    fn f32(&mut self) -> Result<f32, String> {
        Ok(f32::from_le_bytes(self.arr()?))
    }
    fn f64(&mut self) -> Result<f64, String> {
        Ok(f64::from_le_bytes(self.arr()?))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};

    /// The cut-in highway as a corpus split by scene, its scene and its validation fold.
    fn cut_in() -> ([Corpus; 1], Scene, u64) {
        let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway_cut_in.yaml");
        let scene = load_scene(&path, 0, &LoadOptions::default()).unwrap();
        let fold = super::super::trainer::val_fold(&scene.meta.scenario_id);
        let corpus = [Corpus {
            path,
            split: SplitBy::Scene,
        }];
        (corpus, scene, fold)
    }

    fn store(corpus: &[Corpus], cfg: &WindowConfig, fold: u64, dir: &Path) -> WindowStore {
        let holdout = Holdout {
            fold,
            towns: vec![],
        };
        WindowStore::build(corpus, cfg, &holdout, dir, |_, _| ()).unwrap()
    }

    #[test]
    fn a_held_out_town_no_scene_is_in_is_refused_naming_the_towns_there() {
        let (corpus, scene, _) = cut_in();
        let urban = [Corpus {
            path: corpus[0].path.clone(),
            split: SplitBy::Town,
        }];
        let there = town(&scene.meta.scenario_id).to_string();
        let dir = tempfile::tempdir().unwrap();
        let build = |corpora: &[Corpus], towns: Vec<String>| {
            let holdout = Holdout { fold: 0, towns };
            WindowStore::build(
                corpora,
                &WindowConfig::ngsim(),
                &holdout,
                dir.path(),
                |_, _| (),
            )
        };
        let e = build(&urban, vec!["DEU_Atlantis".into()])
            .err()
            .unwrap()
            .to_string();
        assert!(
            e.starts_with("--val-town \"DEU_Atlantis\": no scene is in that town")
                && e.contains(&format!("the towns of the --urban scenes are \"{there}\"")),
            "{e}"
        );
        // Nothing half-written is left in the cache directory.
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        // A town of --data alone (split by scene) is no held-out town either.
        let e = build(&corpus, vec![there.clone()])
            .err()
            .unwrap()
            .to_string();
        assert!(e.contains("held-out towns are for --urban"), "{e}");
        assert!(build(&urban, vec![there]).is_ok());
    }

    #[test]
    fn a_refused_build_leaves_no_directory_it_made() {
        // A held-out town no scene is in refused the run after OUT/windows was made, and the
        // empty directory stayed.
        let (corpus, _, _) = cut_in();
        let urban = [Corpus {
            path: corpus[0].path.clone(),
            split: SplitBy::Town,
        }];
        let dir = tempfile::tempdir().unwrap();
        let cache = dir.path().join("out/windows");
        let holdout = Holdout {
            fold: 0,
            towns: vec!["DEU_Atlantis".into()],
        };
        let lock = lock_out_dir(&dir.path().join("out")).unwrap();
        let e = WindowStore::build(&urban, &WindowConfig::ngsim(), &holdout, &cache, |_, _| ());
        assert!(e.is_err());
        assert!(
            !cache.exists(),
            "the refused build left {}",
            cache.display()
        );
        drop(lock);
        assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
        // A directory that was there before is kept, empty as it was.
        let kept = dir.path().join("kept");
        std::fs::create_dir(&kept).unwrap();
        drop(lock_out_dir(&kept).unwrap());
        assert!(kept.is_dir());
        let e = WindowStore::build(&urban, &WindowConfig::ngsim(), &holdout, &kept, |_, _| ());
        assert!(e.is_err());
        assert!(kept.is_dir());
    }

    #[test]
    fn a_link_planted_at_a_window_file_s_temporary_name_is_removed_not_written_through() {
        // `File::create` opened whatever lay at `train.windows.tmp-PID` and truncated it: a
        // hard link there (a regular file, which the cache check lets by as a leftover) to a
        // file of the user's had that file emptied and filled with windows. A symbolic link
        // planted there after the check was followed the same way.
        let (corpus, _, fold) = cut_in();
        let dir = tempfile::tempdir().unwrap();
        let victim = dir.path().join("victim.txt");
        std::fs::write(&victim, "keep").unwrap();
        let cache = dir.path().join("cache");
        std::fs::create_dir(&cache).unwrap();
        for name in CACHE_FILES {
            let tmp = cache.join(format!("{name}.tmp-{}", std::process::id()));
            std::fs::hard_link(&victim, &tmp).unwrap();
        }
        let st = store(&corpus, &WindowConfig::ngsim(), fold, &cache);
        assert!(st.train_len() + st.val_len() > 0);
        assert_eq!(std::fs::read_to_string(&victim).unwrap(), "keep");
        for name in CACHE_FILES {
            let m = std::fs::symlink_metadata(cache.join(name)).unwrap();
            assert!(m.is_file(), "{name}");
        }
    }

    #[test]
    fn a_scenario_in_two_corpora_is_cut_twice_and_said() {
        let (corpus, _, fold) = cut_in();
        let dir = tempfile::tempdir().unwrap();
        let copy = dir.path().join("copy");
        std::fs::create_dir(&copy).unwrap();
        std::fs::copy(&corpus[0].path, copy.join("again.yaml")).unwrap();
        let cfg = WindowConfig::ngsim();
        let once = store(&corpus, &cfg, fold + 1, &dir.path().join("c1"));
        assert!(once.repeated_scenarios().is_empty());
        let both = [
            corpus[0].clone(),
            Corpus {
                path: copy.clone(),
                split: SplitBy::Scene,
            },
        ];
        let twice = store(&both, &cfg, fold + 1, &dir.path().join("c2"));
        assert_eq!(twice.train_len(), 2 * once.train_len());
        let w = twice.repeated_scenarios();
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].contains("was read 2 times")
                && w[0].contains("highway_cut_in.yaml")
                && w[0].contains("again.yaml"),
            "{w:?}"
        );
    }

    #[test]
    fn a_window_read_back_from_the_store_is_the_window_cut() {
        for route_frame in [false, true] {
            window_read_back(route_frame);
        }
    }

    fn window_read_back(route_frame: bool) {
        // Futures of 4 s, centres observed for 2 s: some windows' futures are complete.
        let cfg = WindowConfig {
            stride: 20,
            min_future: 20,
            route_frame,
            ..WindowConfig::ngsim()
        };
        let dir = tempfile::tempdir().unwrap();
        let (corpus, scene, fold) = cut_in();
        // Fold of the scene, so that it validates, then another, so that it trains.
        for (f, val) in [(fold, true), ((fold + 1) % 10, false)] {
            let store = store(&corpus, &cfg, f, dir.path());
            let cut = windows(&scene, &cfg);
            assert!(!cut.is_empty());
            let (n, get): (usize, Box<dyn Fn(usize) -> Window>) = if val {
                (store.val_len(), Box::new(|i| store.val_window(i).unwrap()))
            } else {
                (
                    store.train_len(),
                    Box::new(|i| store.train_window(i).unwrap()),
                )
            };
            assert_eq!(n, cut.len());
            for (i, w) in cut.iter().enumerate() {
                assert_eq!(&get(i), w, "window {i}");
                assert_eq!(w.routes.len(), if route_frame { w.agents.len() } else { 0 });
            }
            assert_eq!(store.train_len() + store.val_len(), cut.len());
            assert_eq!(store.futures().is_empty(), val);
        }
    }

    #[test]
    fn a_run_reading_a_cache_survives_another_run_rebuilding_it() {
        let cfg = WindowConfig::cities();
        let dir = tempfile::tempdir().unwrap();
        let (corpus, scene, fold) = cut_in();
        let first = store(&corpus, &cfg, (fold + 1) % 10, dir.path());
        // The second run holds the scene out: its train.windows is the bare header.
        let second = store(&corpus, &cfg, fold, dir.path());
        assert_eq!(second.train_len(), 0);
        let cut = windows(&scene, &cfg);
        assert_eq!(first.train_len(), cut.len());
        for (i, w) in cut.iter().enumerate() {
            assert_eq!(&first.train_window(i).unwrap(), w, "window {i}");
        }
        let names: Vec<String> = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        assert!(names.iter().all(|n| !n.contains(".tmp-")), "{names:?}");
    }

    #[test]
    fn a_cache_is_never_among_the_inputs_nor_in_a_directory_of_other_files() {
        // `--cache DATA` wrote train.windows and val.windows among the scenes they were cut
        // from, and `--cache ~/notes` beside the user's files.
        let cfg = WindowConfig::ngsim();
        let root = tempfile::tempdir().unwrap();
        let data = root.path().join("data");
        std::fs::create_dir(&data).unwrap();
        let (corpus, _, fold) = cut_in();
        std::fs::copy(&corpus[0].path, data.join("cut_in.yaml")).unwrap();
        let corpus = [Corpus {
            path: data.clone(),
            split: SplitBy::Scene,
        }];
        let holdout = Holdout {
            fold,
            towns: vec![],
        };
        let build = |dir: &Path| {
            WindowStore::build(&corpus, &cfg, &holdout, dir, |_, _| ())
                .err()
                .map(|e| e.to_string())
        };
        let notes = root.path().join("notes");
        std::fs::create_dir(&notes).unwrap();
        std::fs::write(notes.join("todo.txt"), "mine").unwrap();
        let nested = root.path().join("nested");
        std::fs::create_dir_all(nested.join("train.windows")).unwrap();
        for (dir, want) in [
            (data.clone(), "is the input directory"),
            (data.join("windows"), "is inside the input directory"),
            (data.join("a/../b/c"), "is inside the input directory"),
            (root.path().to_path_buf(), "holds "),
            (notes.clone(), "todo.txt, which is not one of its files"),
            (
                nested.clone(),
                "train.windows, which is not one of its files",
            ),
        ] {
            let e = build(&dir).unwrap_or_else(|| panic!("{} was taken", dir.display()));
            assert!(
                e.contains("the window cache (--cache") && e.contains(want),
                "{e}"
            );
        }
        let names = |d: &Path| -> Vec<String> {
            let mut v: Vec<String> = std::fs::read_dir(d)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            v.sort();
            v
        };
        assert_eq!(names(&data), ["cut_in.yaml"]);
        assert_eq!(names(&notes), ["todo.txt"]);
        // The checkpoint directory is held to the same rule, by the same check.
        for (dir, want) in [
            (data.clone(), "is the input directory"),
            (data.join("ckpt"), "is inside the input directory"),
        ] {
            let e = check_out_dir(&dir, &corpus).unwrap_err().to_string();
            assert!(
                e.contains("the checkpoint directory (--out)") && e.contains(want),
                "{e}"
            );
        }
        assert!(check_out_dir(&notes, &corpus).is_ok());
        // A file, and a directory whose config.json is the user's, are no checkpoint
        // directory: training replaced the config with its own.
        let e = check_out_dir(&notes.join("todo.txt"), &corpus)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("todo.txt: the checkpoint directory (--out) is not a directory"),
            "{e}"
        );
        std::fs::write(notes.join("config.json"), "{\"my\": \"settings\"}").unwrap();
        let e = check_out_dir(&notes, &corpus).unwrap_err().to_string();
        assert!(
            e.contains("config.json, which is not a checkpoint's config"),
            "{e}"
        );
        std::fs::remove_file(notes.join("config.json")).unwrap();
        // Nor is one holding a file training writes without the config every checkpoint has.
        std::fs::write(notes.join("optimizer.safetensors"), "mine").unwrap();
        let e = check_out_dir(&notes, &corpus).unwrap_err().to_string();
        assert!(
            e.contains("optimizer.safetensors but no config.json"),
            "{e}"
        );
        std::fs::remove_file(notes.join("optimizer.safetensors")).unwrap();
        // An earlier run's cache, with what a run stopped while building left, is reused.
        let cache = root.path().join("cache");
        assert_eq!(build(&cache), None);
        std::fs::write(cache.join("val.windows.tmp-4242"), "partial").unwrap();
        // PIDs above the kernel's limit (at most 2^22) belong to no process: what such a
        // build left goes, and a live process's (PID 1) stays.
        std::fs::write(cache.join("train.windows.tmp-4000000001"), "partial").unwrap();
        std::fs::write(cache.join("train.windows.tmp-1"), "partial").unwrap();
        assert_eq!(build(&cache), None);
        assert!(!cache.join("train.windows.tmp-4000000001").exists());
        assert!(cache.join("train.windows.tmp-1").exists());
        std::fs::write(cache.join("val.windows.tmp-"), "x").unwrap();
        assert!(build(&cache).is_some_and(|e| e.contains("val.windows.tmp-,")));
    }

    #[test]
    fn a_damaged_window_file_is_an_error_naming_it() {
        let cfg = WindowConfig::cities();
        let dir = tempfile::tempdir().unwrap();
        let (corpus, _, fold) = cut_in();
        // Another fold, so that the scene trains.
        let store = store(&corpus, &cfg, (fold + 1) % 10, dir.path());
        let path = dir.path().join("train.windows");
        let len = std::fs::metadata(&path).unwrap().len();
        std::fs::OpenOptions::new()
            .write(true)
            .open(&path)
            .unwrap()
            .set_len(len - 10)
            .unwrap();
        let last = store.train_len() - 1;
        let e = store.train_window(last).unwrap_err().to_string();
        assert!(e.contains("train.windows"), "{e}");
    }

    #[test]
    fn towns_split_whole() {
        assert_eq!(town("DEU_Flensburg-10_1_T-1"), "DEU_Flensburg");
        assert_eq!(town("plain"), "plain");
        for fold in 0..10 {
            let h = Holdout {
                fold,
                towns: vec![],
            };
            let a = h.validates("DEU_Flensburg-10_1_T-1", SplitBy::Town);
            let b = h.validates("DEU_Flensburg-77_3_T-1", SplitBy::Town);
            assert_eq!(a, b, "fold {fold}");
        }
        let h = Holdout {
            fold: 0,
            towns: vec!["DEU_Reutlingen".into()],
        };
        assert!(h.validates("DEU_Reutlingen-3_1_T-1", SplitBy::Town));
        assert!(
            !h.validates("DEU_Reutlingen-3_1_T-1", SplitBy::Scene)
                || is_validation("DEU_Reutlingen-3_1_T-1", 0)
        );
    }

    #[test]
    fn an_export_directory_holding_anything_is_refused_before_any_window_is_cut() {
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path().join("export");
        check_export_dir(&out, &[]).unwrap();
        std::fs::create_dir(&out).unwrap();
        check_export_dir(&out, &[]).unwrap();
        std::fs::write(out.join("notes.txt"), "mine").unwrap();
        let e = check_export_dir(&out, &[]).unwrap_err().to_string();
        assert!(e.contains("export") && e.contains("is not empty"), "{e}");
    }

    #[test]
    fn a_scratch_directory_is_made_new_never_taken_over() {
        let prefix = "drivescript-scratch-test";
        let taken = std::env::temp_dir().join(format!("{prefix}-{}-0", std::process::id()));
        std::fs::create_dir_all(&taken).unwrap();
        std::fs::write(taken.join("mine.txt"), "keep").unwrap();
        let made = scratch_dir(prefix).unwrap();
        assert_ne!(made, taken);
        assert_eq!(std::fs::read_dir(&made).unwrap().count(), 0);
        assert_eq!(
            std::fs::read_to_string(taken.join("mine.txt")).unwrap(),
            "keep"
        );
        std::fs::remove_dir_all(&made).unwrap();
        std::fs::remove_dir_all(&taken).unwrap();
    }

    #[test]
    fn a_route_longer_than_its_bytes_is_refused_by_its_slot() {
        let cfg = WindowConfig {
            route_frame: true,
            ..WindowConfig::ngsim()
        };
        let (_, scene, _) = cut_in();
        let w = windows(&scene, &cfg).remove(0);
        let mut b = encode(&w, &cfg);
        assert_eq!(decode(&b, &cfg).unwrap(), w);
        // The first slot's route count sits after the lanes: find it by its own value.
        let n = w.routes[0].len() as u32;
        let at = b.len() - w.routes.iter().map(|r| 4 + r.len() * 8).sum::<usize>();
        assert_eq!(b[at..at + 4], n.to_le_bytes());
        b[at..at + 4].copy_from_slice(&u32::MAX.to_le_bytes());
        let err = decode(&b, &cfg).unwrap_err();
        assert!(
            err.starts_with("agent slot 0: a route of 4294967295 points"),
            "{err}"
        );
        // A route of one point is no line.
        let mut one = w.clone();
        one.routes[1].truncate(1);
        let err = decode(&encode(&one, &cfg), &cfg).unwrap_err();
        assert!(err.starts_with("agent slot 1: route: "), "{err}");
    }
}
