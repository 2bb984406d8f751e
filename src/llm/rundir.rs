//! Guards over a run directory: one process at a time, no file of the user's replaced, nothing
//! written through a link planted inside it.

use std::fs::File;
use std::path::{Path, PathBuf};

use super::LlmError;

/// The lock file every way into a run directory takes (`ask`, `--resume`, `--continue`,
/// `--batch`).
pub const LOCK_FILE: &str = ".drivescript.lock";

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

/// An exclusive hold on a run directory, released when dropped or when the process ends
/// however it ends (an advisory `flock`, so a killed run never leaves a stale lock).
#[derive(Debug)]
pub struct RunLock {
    _file: File,
}

/// Takes the lock of the existing directory `dir`, or says that another process holds it: two
/// processes running the same rounds into the same files would interleave them. `name` is the
/// lock file ([`LOCK_FILE`] for a run; a batch's shards each take their own).
pub fn lock_named(dir: &Path, name: &str) -> Result<RunLock, LlmError> {
    let path = dir.join(name);
    let mut options = std::fs::OpenOptions::new();
    options.read(true).write(true).create(true).truncate(false);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        // A link planted in its place must not make the lock open (or create) a file elsewhere.
        options.custom_flags(libc::O_NOFOLLOW | libc::O_NONBLOCK);
    }
    let file = options
        .open(&path)
        .map_err(|e| err(dir, format!("cannot open its lock file {name}: {e}")))?;
    #[cfg(unix)]
    {
        use std::os::unix::io::AsRawFd;
        // SAFETY: flock on a descriptor this function owns; no memory is involved.
        let rc = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if rc != 0 {
            let e = std::io::Error::last_os_error();
            return Err(err(
                dir,
                if e.kind() == std::io::ErrorKind::WouldBlock {
                    "another drivescript process is running in it (an `ask`, `--resume`, \
                     `--continue` or `--batch`): wait for it to end, or choose another -o"
                        .to_string()
                } else {
                    format!("cannot lock it: {e}")
                },
            ));
        }
    }
    Ok(RunLock { _file: file })
}

/// [`lock_named`] with the run's [`LOCK_FILE`].
pub fn lock(dir: &Path) -> Result<RunLock, LlmError> {
    lock_named(dir, LOCK_FILE)
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

fn is_round_name(name: &str) -> bool {
    name.strip_prefix("round_")
        .is_some_and(|n| !n.is_empty() && n.bytes().all(|b| b.is_ascii_digit()))
}

/// `dir/name` as a directory of the run's own: created when missing; refused when it is a
/// symbolic link or not a directory, so that nothing the run writes lands outside `dir`.
pub fn own_subdir(dir: &Path, name: &str) -> Result<PathBuf, LlmError> {
    let p = dir.join(name);
    match std::fs::symlink_metadata(&p) {
        Ok(m) if m.file_type().is_symlink() => Err(err(
            dir,
            format!(
                "{name} is a symbolic link{}: a run writes only into directories of its own; \
                 remove it",
                std::fs::read_link(&p)
                    .map(|t| format!(" (to {})", t.display()))
                    .unwrap_or_default()
            ),
        )),
        Ok(m) if m.is_dir() => Ok(p),
        Ok(_) => Err(err(
            dir,
            format!("{name} is not a directory: a run writes its files there; remove it"),
        )),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            std::fs::create_dir(&p).map_err(|e| err(dir, format!("cannot create {name}: {e}")))?;
            Ok(p)
        }
        Err(e) => Err(err(dir, format!("{name}: {e}"))),
    }
}

/// Refuses to write the run's file `path` when a symbolic link is in its place: the run would
/// otherwise write wherever the link points.
pub fn check_not_link(path: &Path) -> Result<(), LlmError> {
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_symlink() => Err(err(
            path.parent().unwrap_or(Path::new(".")),
            format!(
                "{} is a symbolic link: a run writes only files of its own; remove it",
                path.file_name().unwrap_or_default().to_string_lossy()
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
    fn round_names_are_round_and_digits() {
        assert!(is_round_name("round_0") && is_round_name("round_12"));
        assert!(!is_round_name("round_") && !is_round_name("round_x") && !is_round_name("r0"));
    }
}
