//! What made a run directory, so that one directory holds one run's outputs.
//!
//! `simulate` writes a [`RunRecord`] as `run.json` before its first rollout and puts it in
//! every rollout: the command, drivescript's version, the checkpoint (a CRC-32C of its
//! weights), the sampler settings with task and seed, the scripts (name and a CRC-32C of their
//! text) and the parameters. A second run into the directory with another record is refused
//! (its `_K.json` would lie beside the first run's and `eval` would score the mixture); the same
//! record continues the run only with `--resume`, which is also how the shards of one run share
//! a directory.

use std::path::Path;

use serde::{Deserialize, Serialize};
use serde_json::Value;

use crate::io::{create_atomic, tfrecord::crc32c};

/// The run record's file name in a run directory.
pub const RUN_FILE: &str = "run.json";

/// The largest run record read: a few hundred bytes in practice.
const MAX_RECORD_BYTES: u64 = 1 << 20;

/// The samples per scene the run in `dir` recorded in its [`RUN_FILE`], where it has a
/// readable one: what `eval --samples` must say to score every sample and only those.
pub fn recorded_samples(dir: &Path) -> Option<u64> {
    let text =
        crate::io::read_regular_text(&dir.join(RUN_FILE), MAX_RECORD_BYTES, "a run record").ok()?;
    let v: Value = serde_json::from_str(&text).ok()?;
    v["settings"]["samples"].as_u64()
}

/// What made a run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RunRecord {
    /// The subcommand (`simulate`).
    pub command: String,
    /// drivescript's version.
    pub version: String,
    /// The checkpoint directory as given.
    pub checkpoint: String,
    /// CRC-32C of the checkpoint's weights file, hex.
    pub weights_crc32c: String,
    /// CRC-32C of the checkpoint's `config.json`, hex: its noise schedule, normaliser and
    /// window shape sample as much as the weights do. Absent in runs written before the
    /// field, which resume without the check.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub config_crc32c: Option<String>,
    /// Task, seed, samples, steps, guidance settings, behaviour: what the sampler was told.
    pub settings: Value,
    /// Each script: its file name and a CRC-32C of its text.
    pub scripts: Vec<(String, String)>,
    /// The `--param` values.
    pub params: String,
}

/// Why a run may not write into a directory.
#[derive(Debug, thiserror::Error)]
pub enum ProvenanceError {
    /// The directory holds another run.
    #[error(
        "{dir}: holds the outputs of another run ({RUN_FILE} differs in {field}: {theirs} there, \
         {ours} here); its rollouts and this run's would mix: choose another -o"
    )]
    OtherRun {
        /// The directory.
        dir: String,
        /// The first field that differs.
        field: String,
        /// Its value in the directory.
        theirs: String,
        /// Its value in this run.
        ours: String,
    },
    /// The directory holds this run's outputs already.
    #[error(
        "{dir}: already holds this run's outputs ({RUN_FILE}); continue it with --resume (which \
         skips the scenes already done, and is how the shards of a run share a directory), or \
         choose another -o"
    )]
    SameRun {
        /// The directory.
        dir: String,
    },
    /// The directory holds shards of this run split another number of ways.
    #[error(
        "{dir}: holds the shards of this run split {theirs} ways ({SHARDS_FILE}); shards of {ours} \
         would leave some scenes in no shard and others in two: give --shard I/{theirs}, or \
         choose another -o"
    )]
    OtherShards {
        /// The directory.
        dir: String,
        /// The count recorded there, as read.
        theirs: String,
        /// This shard's count.
        ours: usize,
    },
    /// The directory holds rollouts (or pictures, or unguided twins) no record accounts for.
    #[error(
        "{dir}: holds files of the kinds a run writes ({example}) but no {RUN_FILE} saying what \
         made them: choose an empty -o"
    )]
    Unattributed {
        /// The directory.
        dir: String,
        /// One such file.
        example: String,
    },
    /// Reading or writing failed.
    #[error("{path}: {message}")]
    Io {
        /// The file.
        path: String,
        /// What failed.
        message: String,
    },
}

/// CRC-32C of a file's bytes, as 8 hex digits.
pub fn file_crc32c(path: &Path) -> Result<String, ProvenanceError> {
    // A checkpoint's weights: regular files only (a FIFO would wait forever).
    let bytes = crate::io::read_regular(path, 4 << 30, "checkpoint weights").map_err(|e| {
        ProvenanceError::Io {
            path: path.display().to_string(),
            message: e.to_string(),
        }
    })?;
    Ok(text_crc32c(&bytes))
}

/// CRC-32C of bytes, as 8 hex digits.
pub fn text_crc32c(bytes: &[u8]) -> String {
    format!("{:08x}", crc32c(bytes))
}

impl RunRecord {
    /// Claims `dir` for this run: a fresh directory gets the record; one holding the same
    /// record is continued only when `resume`; anything else is refused. Returns whether
    /// this call wrote the record.
    pub fn claim(&self, dir: &Path, resume: bool) -> Result<bool, ProvenanceError> {
        let file = dir.join(RUN_FILE);
        let shown = dir.display().to_string();
        let io = |p: &Path, e: String| ProvenanceError::Io {
            path: p.display().to_string(),
            message: e,
        };
        // Twice at most: a run that loses the race to create the record compares with the
        // winner's.
        for _ in 0..2 {
            // A regular file within a cap: a FIFO planted as run.json waited for a writer
            // forever.
            match crate::io::read_regular_text(&file, MAX_RECORD_BYTES, "a run record") {
                Ok(text) => {
                    let theirs: Value = serde_json::from_str(&text)
                        .map_err(|e| io(&file, format!("not a run record: {e}")))?;
                    let mut ours = serde_json::to_value(self).expect("records serialise");
                    if theirs.get("config_crc32c").is_none() {
                        ours.as_object_mut()
                            .expect("a record is an object")
                            .remove("config_crc32c");
                    }
                    if let Some((field, a, b)) = first_difference("", &theirs, &ours) {
                        return Err(ProvenanceError::OtherRun {
                            dir: shown,
                            field,
                            theirs: a,
                            ours: b,
                        });
                    }
                    return if resume {
                        Ok(false)
                    } else {
                        Err(ProvenanceError::SameRun { dir: shown })
                    };
                }
                Err(crate::io::IoError::Read { source, .. })
                    if source.kind() == std::io::ErrorKind::NotFound =>
                {
                    if dir.exists() {
                        // Every name a run writes: rollouts and costs (.json), pictures
                        // (.gif) and, with --auto, unguided/SCENARIO_K.json. Only the first was
                        // looked for: a user's unguided/ID_0.json or ID_0.gif was replaced.
                        let kinds = |d: &Path, exts: &[&str]| -> Result<Option<String>, _> {
                            if !d.is_dir() {
                                return Ok(None);
                            }
                            // Files only: a directory at such a name is never replaced
                            // (writing there fails, naming it).
                            Ok(std::fs::read_dir(d)
                                .map_err(|e| io(d, e.to_string()))?
                                .filter_map(|e| e.ok())
                                .filter(|e| e.file_type().is_ok_and(|t| !t.is_dir()))
                                .map(|e| e.file_name().to_string_lossy().into_owned())
                                .find(|n| exts.iter().any(|x| n.ends_with(x))))
                        };
                        let rollouts = match kinds(dir, &[".json", ".gif"])? {
                            Some(n) => Some(n),
                            None => kinds(&dir.join("unguided"), &[".json"])?
                                .map(|n| format!("unguided/{n}")),
                        };
                        if let Some(example) = rollouts {
                            return Err(ProvenanceError::Unattributed {
                                dir: shown,
                                example,
                            });
                        }
                    }
                    let text = serde_json::to_string_pretty(self).expect("records serialise");
                    if create_atomic(&file, text.as_bytes())
                        .map_err(|e| io(&file, e.to_string()))?
                    {
                        return Ok(true);
                    }
                }
                Err(e) => return Err(io(&file, e.reason())),
            }
        }
        Err(io(
            &file,
            "it appeared and vanished while this run claimed the directory".into(),
        ))
    }
}

/// The file of a sharded run directory that records into how many shards its scenes are
/// split. Not in the [`RunRecord`]: rollouts carry the record, and a sharded run's are the
/// same as an unsharded one's.
pub const SHARDS_FILE: &str = "run.shards";

/// Claims `dir` for the shards of a run split `count` ways: the first shard records the count,
/// the others must give the same. Shards 0/2 and then 1/3 into one directory left some scenes
/// in no shard (and others in two) without a word: each split is a partition only of itself.
pub fn claim_shards(dir: &Path, count: usize) -> Result<(), ProvenanceError> {
    let file = dir.join(SHARDS_FILE);
    let io = |e: String| ProvenanceError::Io {
        path: file.display().to_string(),
        message: e,
    };
    for _ in 0..2 {
        match crate::io::read_regular_text(&file, 64, "a shard count") {
            Ok(text) => {
                let theirs = text.trim();
                if theirs == count.to_string() {
                    return Ok(());
                }
                // A damaged file ("garbage", empty, 0) was read as another split, and the
                // message asked for `--shard I/garbage`, a flag no run can be given.
                let valid = theirs
                    .parse::<usize>()
                    .is_ok_and(|n| (1..=crate::io::shard::MAX_SHARDS).contains(&n));
                if !valid {
                    return Err(io(format!(
                        "holds \"{}\", not a number of shards (1 to {}): the file is damaged; \
                         it records how many ways this run's scenes are split (the N of the \
                         first --shard I/N into this directory): write that number into it, \
                         or choose another -o",
                        crate::io::name::shown(theirs),
                        crate::io::shard::MAX_SHARDS
                    )));
                }
                return Err(ProvenanceError::OtherShards {
                    dir: dir.display().to_string(),
                    theirs: crate::io::name::shown(theirs),
                    ours: count,
                });
            }
            Err(crate::io::IoError::Read { source, .. })
                if source.kind() == std::io::ErrorKind::NotFound =>
            {
                if create_atomic(&file, format!("{count}\n").as_bytes())
                    .map_err(|e| io(e.to_string()))?
                {
                    return Ok(());
                }
            }
            Err(e) => return Err(io(e.reason())),
        }
    }
    Err(io(
        "it appeared and vanished while this shard claimed the directory".into(),
    ))
}

/// The first field (a dotted path) where two JSON values differ, with both values.
fn first_difference(at: &str, a: &Value, b: &Value) -> Option<(String, String, String)> {
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            keys.into_iter().find_map(|k| {
                let path = if at.is_empty() {
                    k.clone()
                } else {
                    format!("{at}.{k}")
                };
                first_difference(
                    &path,
                    x.get(k).unwrap_or(&Value::Null),
                    y.get(k).unwrap_or(&Value::Null),
                )
            })
        }
        _ if a == b => None,
        _ => Some((at.to_string(), recorded(a), recorded(b))),
    }
}

/// A recorded value as a user reads it: `null` is a setting left to its default (the model's
/// horizon, say), which "null" did not say.
fn recorded(v: &Value) -> String {
    match v {
        Value::Null => "not given (the default)".into(),
        _ => v.to_string(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_damaged_shard_count_is_said_so_not_taken_for_another_split() {
        let dir = tempfile::tempdir().unwrap();
        for damaged in ["garbage\n", "", "0\n", "99999999999999999999\n"] {
            std::fs::write(dir.path().join(SHARDS_FILE), damaged).unwrap();
            let e = claim_shards(dir.path(), 2).unwrap_err().to_string();
            assert!(
                e.contains("run.shards: holds \"")
                    && e.contains("not a number of shards (1 to 1000000): the file is damaged")
                    && !e.contains("give --shard I/"),
                "{damaged:?}: {e}"
            );
        }
        // Another valid split is still refused as one.
        std::fs::write(dir.path().join(SHARDS_FILE), "3\n").unwrap();
        let e = claim_shards(dir.path(), 2).unwrap_err().to_string();
        assert!(e.contains("give --shard I/3"), "{e}");
        std::fs::write(dir.path().join(SHARDS_FILE), "2\n").unwrap();
        claim_shards(dir.path(), 2).unwrap();
    }

    fn record(seed: u64) -> RunRecord {
        RunRecord {
            command: "simulate".into(),
            version: "0.1.0".into(),
            checkpoint: "data/checkpoint".into(),
            weights_crc32c: "0123abcd".into(),
            config_crc32c: Some("4567cdef".into()),
            settings: serde_json::json!({"task": "unconditional", "seed": seed}),
            scripts: vec![("cut_in.rhai".into(), "deadbeef".into())],
            params: String::new(),
        }
    }

    #[test]
    fn a_run_record_that_is_not_a_regular_file_is_refused_not_waited_on() {
        let dir = tempfile::tempdir().unwrap();
        let made = std::process::Command::new("mkfifo")
            .arg(dir.path().join(RUN_FILE))
            .status();
        assert!(made.is_ok_and(|s| s.success()), "mkfifo");
        let e = record(1).claim(dir.path(), true).unwrap_err().to_string();
        assert!(
            e.contains("run.json") && e.contains("not a regular file"),
            "{e}"
        );
        assert_eq!(recorded_samples(dir.path()), None);
    }

    #[test]
    fn the_samples_a_run_recorded_are_read_back() {
        let dir = tempfile::tempdir().unwrap();
        let mut r = record(1);
        r.settings["samples"] = 4.into();
        r.claim(dir.path(), false).unwrap();
        assert_eq!(recorded_samples(dir.path()), Some(4));
    }

    #[test]
    fn a_directory_takes_one_run() {
        let dir = tempfile::tempdir().unwrap();
        record(1).claim(dir.path(), false).unwrap();
        assert!(dir.path().join(RUN_FILE).exists());
        // The same run again: only with --resume.
        let e = record(1).claim(dir.path(), false).unwrap_err().to_string();
        assert!(e.contains("--resume"), "{e}");
        record(1).claim(dir.path(), true).unwrap();
        // Another run: never, and the message says what differs.
        let e = record(2).claim(dir.path(), true).unwrap_err().to_string();
        assert!(e.contains("settings.seed: 1 there, 2 here"), "{e}");
        // A setting left to its default is said so, not printed as JSON's null.
        let mut defaulted = record(1);
        defaulted.settings["horizon"] = serde_json::Value::Null;
        let mut given = record(1);
        given.settings["horizon"] = 20.into();
        let other = tempfile::tempdir().unwrap();
        given.claim(other.path(), false).unwrap();
        let e = defaulted.claim(other.path(), true).unwrap_err().to_string();
        assert!(
            e.contains("settings.horizon: 20 there, not given (the default) here"),
            "{e}"
        );
    }

    #[test]
    fn rollouts_without_a_record_are_not_mixed_with() {
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("scene_0.json"), "{}").unwrap();
        let e = record(1).claim(dir.path(), true).unwrap_err().to_string();
        assert!(
            e.contains("scene_0.json") && e.contains("no run.json"),
            "{e}"
        );
    }

    #[test]
    fn pictures_and_unguided_twins_without_a_record_are_not_replaced() {
        // Only top-level .json files were looked for: `simulate --auto` replaced a user's
        // unguided/ID_0.json and ID_0.gif in a fresh -o, exit 0.
        for (name, shown) in [
            ("scene_0.gif", "scene_0.gif"),
            ("unguided/scene_0.json", "unguided/scene_0.json"),
        ] {
            let dir = tempfile::tempdir().unwrap();
            let f = dir.path().join(name);
            std::fs::create_dir_all(f.parent().unwrap()).unwrap();
            std::fs::write(&f, "my notes").unwrap();
            let e = record(1).claim(dir.path(), false).unwrap_err().to_string();
            assert!(e.contains(shown) && e.contains("no run.json"), "{e}");
            assert!(!dir.path().join(RUN_FILE).exists());
        }
        // Other files (a README) leave the directory free.
        let dir = tempfile::tempdir().unwrap();
        std::fs::write(dir.path().join("README.md"), "notes").unwrap();
        std::fs::create_dir(dir.path().join("unguided")).unwrap();
        assert!(record(1).claim(dir.path(), false).unwrap());
    }

    #[test]
    fn of_runs_racing_for_a_fresh_directory_exactly_one_wins() {
        for round in 0..20 {
            let dir = tempfile::tempdir().unwrap();
            let out = dir.path().join("out");
            let n = 8;
            let barrier = std::sync::Barrier::new(n);
            let won: Vec<bool> = std::thread::scope(|s| {
                let handles: Vec<_> = (0..n)
                    .map(|k| {
                        let (out, barrier) = (&out, &barrier);
                        s.spawn(move || {
                            barrier.wait();
                            record(k as u64).claim(out, true).is_ok()
                        })
                    })
                    .collect();
                handles.into_iter().map(|h| h.join().unwrap()).collect()
            });
            assert_eq!(
                won.iter().filter(|w| **w).count(),
                1,
                "round {round}: {won:?}"
            );
            let text = std::fs::read_to_string(out.join(RUN_FILE)).unwrap();
            let seed = won.iter().position(|w| *w).unwrap();
            assert!(text.contains(&format!("\"seed\": {seed}")), "{text}");
        }
    }
}
