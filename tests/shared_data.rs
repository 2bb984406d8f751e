//! Every scene of the development corpus in ../shared/data reads. The corpus is not part of the
//! repository, so this test has its own harness (tests/common/harness.rs): without the corpus
//! it reports "skipped", not "ok".

use std::path::PathBuf;
use std::process::ExitCode;

use drivescript::io::{discover, load_scenes, LoadOptions};

mod common;
use common::harness::{single, Outcome};

const NAME: &str = "every_shared_scene_reads";

/// The problems found, or the number of scenes read.
fn check(root: &PathBuf) -> Result<usize, Vec<String>> {
    let mut n = 0;
    let mut failures = Vec::new();
    let sources = discover(root).map_err(|e| vec![e.to_string()])?;
    for src in sources {
        match load_scenes(&src, &LoadOptions::default()) {
            Ok(scenes) => {
                for s in &scenes {
                    if s.num_steps() == 0 || s.agents.is_empty() {
                        failures.push(format!("{}: no steps or no agents", src.display()));
                    }
                    if s.map.lanes().is_empty() || s.map.road_edges().is_empty() {
                        failures.push(format!("{}: no lanes or no road edges", src.display()));
                    }
                }
                n += scenes.len();
            }
            Err(e) => failures.push(e.to_string()),
        }
    }
    if n < 113 {
        failures.push(format!("only {n} scenes found under {}", root.display()));
    }
    if failures.is_empty() {
        Ok(n)
    } else {
        Err(failures)
    }
}

fn main() -> ExitCode {
    single(NAME, || {
        let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
        if !root.exists() {
            return Ok(Outcome::Skipped(format!(
                "{} not found (development corpus only)",
                root.display()
            )));
        }
        check(&root)
            .map(|n| Outcome::Passed(format!("{n} scenes")))
            .map_err(|failures| failures.join("\n"))
    })
}
