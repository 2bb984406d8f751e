//! Guards over a run directory: one process at a time, no file of the user's replaced, nothing
//! written through a link planted inside it.

use std::fs::File;
use std::path::{Path, PathBuf};

use super::LlmError;
use crate::io::shard::Shard;

/// The lock file every way into a run directory takes: `ask`, `--resume`, `--continue`,
/// `--replay` and `demo` exclusively ([`lock`]); `--batch` shared ([`lock_batch`]), so that
/// the shards of one batch run side by side into one `-o` while no single run can start there,
/// and no batch can start where a single run is going on.
pub const LOCK_FILE: &str = ".drivescript.lock";

/// The lock file of a whole (unsharded) batch, beside [`LOCK_FILE`] in its `-o`. Left there
/// after the batch ends: it and the shards' ones ([`batch_lock_name`]) mark the directory as
/// a batch's. A batch that fails before any result removes the ones it created
/// ([`Before::restore`]).
pub const BATCH_LOCK_FILE: &str = ".drivescript.batch.lock";

/// The names a run writes at the top of its directory: one of them there before a run starts
/// is the user's (without `state.json` drivescript never ran there), and must not be replaced.
pub const RUN_FILES: &[&str] = &[
    "state.json",
    "transcript.json",
    "report.md",
    "final.rhai",
    "final.gif",
];

fn err(dir: &Path, message: impl Into<String>) -> LlmError {
    LlmError::Run {
        dir: dir.to_path_buf(),
        message: message.into(),
    }
}

/// A file or directory inside a run directory, named itself.
fn file_err(path: &Path, message: impl Into<String>) -> LlmError {
    LlmError::RunFile {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

/// A batch's output directory is not a run directory: its errors name it plainly.
fn batch_err(dir: &Path, message: impl Into<String>) -> LlmError {
    LlmError::Input {
        path: dir.to_path_buf(),
        message: message.into(),
    }
}

/// What a directory holds, by the marks drivescript leaves there: a directory holds one kind
/// of run, since a batch's summary and a single run's files would be told apart by nobody.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// One `ask` run (its `state.json`).
    Run,
    /// An `ask --batch` (its lock files, or a summary a batch wrote).
    Batch,
}

impl Kind {
    fn words(self) -> &'static str {
        match self {
            Kind::Run => "a single `ask` run (state.json)",
            Kind::Batch => "an `ask --batch` run (its summary and runs/)",
        }
    }
}

/// The lock file name of a batch, or of one of its shards.
pub fn batch_lock_name(shard: Option<Shard>) -> String {
    match shard {
        Some(sh) => format!(".drivescript.batch-{}-of-{}.lock", sh.index, sh.count),
        None => BATCH_LOCK_FILE.to_string(),
    }
}

fn is_batch_mark(name: &str) -> bool {
    name == BATCH_LOCK_FILE
        || name
            .strip_prefix(".drivescript.batch-")
            .and_then(|r| r.strip_suffix(".lock"))
            .and_then(|r| r.split_once("-of-"))
            .is_some_and(|(i, n)| i.parse::<usize>().is_ok() && n.parse::<usize>().is_ok())
}

/// The kinds of run `dir` holds (none for a new or foreign directory; both for one that an
/// earlier drivescript let a batch and a single run share).
pub fn kinds(dir: &Path) -> Vec<Kind> {
    let mut found = Vec::new();
    if std::fs::symlink_metadata(dir.join("state.json")).is_ok() {
        found.push(Kind::Run);
    }
    let batch_lock = std::fs::read_dir(dir).is_ok_and(|entries| {
        entries
            .filter_map(|e| e.ok())
            .any(|e| is_batch_mark(&e.file_name().to_string_lossy()))
    });
    // Batches written before their lock files were kept have only their summary to show.
    let batch_summary = || {
        crate::io::read_regular_text(&dir.join("summary.md"), 1 << 20, "a summary")
            .is_ok_and(|t| t.starts_with("# drivescript ask --batch"))
    };
    if batch_lock || batch_summary() {
        found.push(Kind::Batch);
    }
    found
}

/// Refuses `dir` for a run of kind `wanted` when it holds a run of another kind: a batch's
/// `-o` holding a single run's files, or the reverse, would be read back as neither.
/// `advice` says what to do instead.
pub fn check_kind(dir: &Path, wanted: Kind, advice: &str) -> Result<(), LlmError> {
    let others: Vec<Kind> = kinds(dir).into_iter().filter(|k| *k != wanted).collect();
    let Some(other) = others.first() else {
        return Ok(());
    };
    let message = format!(
        "it holds {}, and a directory holds one kind of run, so {} does not go there: {advice}",
        other.words(),
        match wanted {
            Kind::Run => "a single `ask` run",
            Kind::Batch => "an `ask --batch` run",
        }
    );
    Err(match wanted {
        Kind::Run => err(dir, message),
        Kind::Batch => batch_err(dir, message),
    })
}

/// An exclusive hold on a run directory, released when dropped or when the process ends
/// however it ends (an advisory `flock`, so a killed run never leaves a stale lock).
#[derive(Debug)]
pub struct RunLock {
    _file: File,
}

impl RunLock {
    /// Whether the locked file is the one `path` names now (not one removed meanwhile).
    fn is_at(&self, path: &Path) -> bool {
        #[cfg(unix)]
        {
            use std::os::unix::fs::MetadataExt;
            match (self._file.metadata(), std::fs::symlink_metadata(path)) {
                (Ok(held), Ok(named)) => held.dev() == named.dev() && held.ino() == named.ino(),
                _ => false,
            }
        }
        #[cfg(not(unix))]
        {
            path.exists()
        }
    }

    /// Removes the lock file `path` this lock holds, when no other process holds it too
    /// (taken exclusively first, without waiting); says whether it was removed. Removed while
    /// still locked, so that no process can lock it in between ([`flock`] retries a lock
    /// taken on a file removed since).
    fn remove_file(self, path: &Path) -> std::io::Result<bool> {
        if !self.is_at(path) {
            return Ok(false);
        }
        #[cfg(unix)]
        {
            use std::os::unix::io::AsRawFd;
            // SAFETY: flock on a descriptor this lock owns; no memory is involved.
            let rc = unsafe { libc::flock(self._file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
            if rc != 0 {
                let e = std::io::Error::last_os_error();
                return if e.kind() == std::io::ErrorKind::WouldBlock {
                    Ok(false)
                } else {
                    Err(e)
                };
            }
        }
        std::fs::remove_file(path)?;
        Ok(true)
    }
}

/// What a batch's output directory held before the batch started: a batch that fails before
/// any result (an unreachable server at the first request, a pair that cannot start, a
/// summary of the user's in the way) leaves the directory as it found it ([`Before::restore`]),
/// so that it is not marked as a batch's, and a later single run or batch there is not
/// refused or confused by it. A batch with a result (a summary, or a reply the model was paid
/// for) keeps its marks: it is continued by running it again.
#[derive(Debug, Clone)]
pub struct Before {
    out: PathBuf,
    batch_lock: String,
    had_out: bool,
    had_lock: bool,
    had_batch_lock: bool,
    had_runs: bool,
    had_rollouts: bool,
}

impl Before {
    /// What `out` holds now, for a batch (or shard `shard` of one) about to run there.
    pub fn of(out: &Path, shard: Option<Shard>) -> Self {
        let has = |name: &str| std::fs::symlink_metadata(out.join(name)).is_ok();
        let batch_lock = batch_lock_name(shard);
        Self {
            out: out.to_path_buf(),
            had_out: std::fs::symlink_metadata(out).is_ok(),
            had_lock: has(LOCK_FILE),
            had_batch_lock: has(&batch_lock),
            had_runs: has("runs"),
            had_rollouts: has("rollouts"),
            batch_lock,
        }
    }

    /// Removes what the batch added: `pair`, the run directory of a pair it created (the
    /// pair's session already dropped), `runs/` and `rollouts/` where it created them and they
    /// are empty, its lock files where it created them and no other process holds them (a
    /// shard beside it keeps the shared one), and `out` where it created it and it is empty.
    /// `locks` are the batch's ([`lock_batch`]), released here. Returns what could not be
    /// removed, in words (empty when all went).
    pub fn restore(&self, pair: Option<&Path>, locks: Option<(RunLock, RunLock)>) -> Vec<String> {
        let mut left = Vec::new();
        let mut note = |p: &Path, e: std::io::Error| {
            left.push(format!("{}: cannot remove it: {e}", p.display()));
        };
        let gone_or_kept = |r: std::io::Result<()>| match r {
            Err(e)
                if e.kind() == std::io::ErrorKind::NotFound
                    || e.kind() == std::io::ErrorKind::DirectoryNotEmpty =>
            {
                Ok(())
            }
            other => other,
        };
        if let Some(p) = pair {
            if let Err(e) = gone_or_kept(std::fs::remove_dir_all(p)) {
                note(p, e);
            }
        }
        for (had, name) in [(self.had_runs, "runs"), (self.had_rollouts, "rollouts")] {
            let p = self.out.join(name);
            // Left where another shard has put its pairs there meanwhile.
            if !had {
                if let Err(e) = gone_or_kept(std::fs::remove_dir(&p)) {
                    note(&p, e);
                }
            }
        }
        if let Some((shared, own)) = locks {
            for (had, name, lock) in [
                (self.had_batch_lock, self.batch_lock.as_str(), own),
                (self.had_lock, LOCK_FILE, shared),
            ] {
                let p = self.out.join(name);
                if had {
                    drop(lock);
                } else if let Err(e) = lock.remove_file(&p) {
                    note(&p, e);
                }
            }
        }
        if !self.had_out {
            if let Err(e) = gone_or_kept(std::fs::remove_dir(&self.out)) {
                note(&self.out, e);
            }
        }
        left
    }
}

/// Why a lock is not to be had: who holds it, as far as the directory's marks tell.
fn held_by(dir: &Path) -> String {
    let kinds = kinds(dir);
    format!(
        "another drivescript process is running in it ({}): wait for it to end, or choose \
         another -o",
        if kinds.contains(&Kind::Batch) {
            "an `ask --batch`"
        } else if kinds.contains(&Kind::Run) {
            "an `ask` run, its `--resume` or its `--continue`"
        } else {
            "an `ask`, `--resume`, `--continue` or `--batch`"
        }
    )
}

/// Why [`flock`] could not lock.
enum LockError {
    /// Another process holds the directory (in words, [`held_by`]).
    Held(String),
    /// The lock file itself (its path) cannot be opened or locked.
    File(PathBuf, String),
}

impl LockError {
    /// As an error of the run directory `dir`: a held lock is the directory's, a lock file
    /// that cannot be used is named itself.
    fn of_run(self, dir: &Path) -> LlmError {
        match self {
            LockError::Held(m) => err(dir, m),
            LockError::File(p, m) => file_err(&p, m),
        }
    }

    /// As an error of the batch output directory `out`.
    fn of_batch(self, out: &Path) -> LlmError {
        match self {
            LockError::Held(m) => batch_err(out, m),
            LockError::File(p, m) => batch_err(&p, m),
        }
    }
}

/// Takes the lock file `name` of the existing directory `dir`, exclusively or shared.
fn flock_once(dir: &Path, name: &str, exclusive: bool) -> Result<RunLock, LockError> {
    let path = dir.join(name);
    let mut options = std::fs::OpenOptions::new();
    options.read(true).write(true).create(true).truncate(false);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        // A link planted in its place must not make the lock open (or create) a file elsewhere.
        options.custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK);
    }
    let file = options.open(&path).map_err(|e| {
        LockError::File(
            path.clone(),
            format!("cannot open it (drivescript's lock file for the directory): {e}"),
        )
    })?;
    #[cfg(unix)]
    {
        use std::os::unix::io::AsRawFd;
        let how = if exclusive {
            libc::LOCK_EX
        } else {
            libc::LOCK_SH
        };
        // SAFETY: flock on a descriptor this function owns; no memory is involved.
        let rc = unsafe { libc::flock(file.as_raw_fd(), how | libc::LOCK_NB) };
        if rc != 0 {
            let e = std::io::Error::last_os_error();
            return Err(if e.kind() == std::io::ErrorKind::WouldBlock {
                LockError::Held(held_by(dir))
            } else {
                LockError::File(path, format!("cannot lock it: {e}"))
            });
        }
    }
    #[cfg(not(unix))]
    let _ = exclusive;
    Ok(RunLock { _file: file })
}

/// [`flock_once`] until the lock is on the file that `dir/name` names: a batch that failed
/// before any result removes its lock files ([`Before::restore`]), and a process that opened
/// one just before may then hold a lock on a removed file, which locks nothing.
fn flock(dir: &Path, name: &str, exclusive: bool) -> Result<RunLock, LockError> {
    let path = dir.join(name);
    for _ in 0..16 {
        let lock = flock_once(dir, name, exclusive)?;
        if lock.is_at(&path) {
            return Ok(lock);
        }
    }
    Err(LockError::File(
        path,
        "it was removed and created again while this process took it, 16 times: another \
         drivescript process is starting and failing in the directory; try again"
            .into(),
    ))
}

/// Takes the exclusive lock of the existing run directory `dir`, or says that another process
/// holds it: two processes running the same rounds into the same files would interleave
/// them, and a batch running there would mix its files with the run's.
pub fn lock(dir: &Path) -> Result<RunLock, LlmError> {
    flock(dir, LOCK_FILE, true).map_err(|e| e.of_run(dir))
}

/// Takes a batch's locks on its existing output directory `out`: [`LOCK_FILE`] shared (the
/// shards of one batch share `out` by design; a single run there takes it exclusively) and
/// the batch's or shard's own ([`batch_lock_name`]) exclusively (one process per shard). Then
/// refuses an `out` that holds a single run ([`check_kind`]): checked under the lock, where no
/// single run can be starting.
pub fn lock_batch(out: &Path, shard: Option<Shard>) -> Result<(RunLock, RunLock), LlmError> {
    let advice = "choose another -o for the batch";
    // Before the batch's own lock file marks `out` as a batch's.
    check_kind(out, Kind::Batch, advice)?;
    let shared = flock(out, LOCK_FILE, false).map_err(|e| e.of_batch(out))?;
    check_kind(out, Kind::Batch, advice)?;
    let own = flock(out, &batch_lock_name(shard), true).map_err(|e| e.of_batch(out))?;
    Ok((shared, own))
}

/// Refuses to start a run in `dir` when it already holds a file a run writes ([`RUN_FILES`])
/// or a `round_N` entry: with no `state.json` there, drivescript did not write them, and the
/// run would replace them (or, for a `round_N` link, write through it outside `dir`).
pub fn check_fresh(dir: &Path) -> Result<(), LlmError> {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return Ok(());
    };
    let mut found: Vec<String> = entries
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| RUN_FILES.contains(&n.as_str()) || is_round_name(n))
        .collect();
    if found.is_empty() {
        return Ok(());
    }
    found.sort();
    Err(err(
        dir,
        format!(
            "it already holds {}, which a run writes; drivescript did not write {} here (there is \
             no state.json), so it will not replace {}: move {}, or choose a new or empty -o",
            found.join(", "),
            if found.len() == 1 { "it" } else { "them" },
            if found.len() == 1 { "it" } else { "them" },
            if found.len() == 1 { "it" } else { "them" },
        ),
    ))
}

/// Removes the run in `dir` (only the files a run writes, [`RUN_FILES`] and `round_N/`) so
/// that a new one can start there; anything else is left alone, and nothing is removed where
/// there is no `state.json` (drivescript did not run there). Called under the run's [`lock`].
pub fn clear_run(dir: &Path) -> Result<(), LlmError> {
    if std::fs::symlink_metadata(dir.join("state.json")).is_err() {
        return Ok(());
    }
    let entries = std::fs::read_dir(dir).map_err(|e| err(dir, format!("cannot list it: {e}")))?;
    for e in entries {
        let e = e.map_err(|e| err(dir, format!("cannot list it: {e}")))?;
        let name = e.file_name().to_string_lossy().into_owned();
        let p = e.path();
        let removed = match e.file_type() {
            // A link (to a directory or not) goes, never what it points to.
            Ok(t) if t.is_dir() && is_round_name(&name) => std::fs::remove_dir_all(&p),
            Ok(t)
                if !t.is_dir() && (RUN_FILES.contains(&name.as_str()) || is_round_name(&name)) =>
            {
                std::fs::remove_file(&p)
            }
            _ => Ok(()),
        };
        removed.map_err(|e| {
            file_err(
                &p,
                format!(
                    "cannot remove it (the earlier run wrote it, and a new one replaces it): {e}"
                ),
            )
        })?;
    }
    Ok(())
}

fn is_round_name(name: &str) -> bool {
    name.strip_prefix("round_")
        .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
}

/// `dir/name` as a directory of the run's own: created when missing; refused when it is a
/// symbolic link or not a directory, so that nothing the run writes lands outside `dir`.
/// Errors name `dir/name`, the entry that is wrong.
pub fn own_subdir(dir: &Path, name: &str) -> Result<PathBuf, LlmError> {
    let p = dir.join(name);
    match std::fs::symlink_metadata(&p) {
        Ok(m) if m.file_type().is_symlink() => Err(file_err(
            &p,
            format!(
                "a symbolic link{}, where the run keeps a directory of its own (it writes only \
                 into directories of its own): remove it",
                std::fs::read_link(&p)
                    .map(|t| format!(" (to {})", t.display()))
                    .unwrap_or_default()
            ),
        )),
        Ok(m) if m.is_dir() => Ok(p),
        Ok(_) => Err(file_err(
            &p,
            "not a directory: the run writes its files into a directory of its own there; \
             remove it",
        )),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            std::fs::create_dir(&p).map_err(|e| {
                file_err(
                    &p,
                    format!("cannot create it (the run writes its files there): {e}"),
                )
            })?;
            Ok(p)
        }
        Err(e) => Err(file_err(
            &p,
            format!("cannot read it (the run keeps a directory there): {e}"),
        )),
    }
}

/// Refuses to write the run's file `path` when a symbolic link is in its place: the run would
/// otherwise write wherever the link points. The error names `path`.
pub fn check_not_link(path: &Path) -> Result<(), LlmError> {
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_symlink() => Err(file_err(
            path,
            format!(
                "a symbolic link{}, where drivescript writes a file or directory of its own \
                 (never through a link): remove it",
                std::fs::read_link(path)
                    .map(|t| format!(" (to {})", t.display()))
                    .unwrap_or_default()
            ),
        )),
        _ => Ok(()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_second_lock_on_one_directory_is_refused_until_the_first_is_dropped() {
        let dir = tempfile::tempdir().unwrap();
        let first = lock(dir.path()).unwrap();
        let e = lock(dir.path()).unwrap_err().to_string();
        assert!(e.contains("another drivescript process is running"), "{e}");
        drop(first);
        lock(dir.path()).unwrap();
    }

    #[test]
    fn a_failed_batch_removes_its_own_lock_files_but_not_one_another_shard_holds() {
        let names = |d: &Path| -> Vec<String> {
            let mut v: Vec<String> = std::fs::read_dir(d)
                .unwrap()
                .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
                .collect();
            v.sort();
            v
        };
        let dir = tempfile::tempdir().unwrap();
        let out = dir.path();
        let before = Before::of(out, None);
        let locks = lock_batch(out, None).unwrap();
        assert_eq!(kinds(out), vec![Kind::Batch]);
        assert!(before.restore(None, Some(locks)).is_empty());
        assert!(names(out).is_empty(), "{:?}", names(out));
        assert!(kinds(out).is_empty());
        // Shard 0 fails while shard 1 runs: shard 1's marks and the shared lock file stay.
        let shard = |i: usize| Some(format!("{i}/2").parse::<Shard>().unwrap());
        let one = lock_batch(out, shard(1)).unwrap();
        let before = Before::of(out, shard(0));
        let zero = lock_batch(out, shard(0)).unwrap();
        assert!(before.restore(None, Some(zero)).is_empty());
        assert_eq!(names(out), [batch_lock_name(shard(1)).as_str(), LOCK_FILE]);
        drop(one);
        // A lock taken afterwards is on the file its name gives.
        let again = lock(out).unwrap();
        assert!(again.is_at(&out.join(LOCK_FILE)));
    }

    #[test]
    fn round_names_are_round_and_digits() {
        assert!(is_round_name("round_0") && is_round_name("round_12"));
        assert!(!is_round_name("round_") && !is_round_name("round_x") && !is_round_name("r0"));
    }
}
