//! Every scene of the development corpus in ../shared/data reads. The corpus is not part of the
//! repository: without it this test says so and passes.

use std::path::PathBuf;

use drivescript::io::{discover, load_scenes, LoadOptions};

#[test]
fn every_shared_scene_reads() {
    let root = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../shared/data");
    if !root.exists() {
        eprintln!(
            "skipped: {} not found (development corpus only)",
            root.display()
        );
        return;
    }
    let mut n = 0;
    let mut failures = Vec::new();
    for src in discover(&root).unwrap() {
        match load_scenes(&src, &LoadOptions::default()) {
            Ok(scenes) => {
                for s in &scenes {
                    assert!(
                        s.num_steps() > 0 && !s.agents.is_empty(),
                        "{}",
                        src.display()
                    );
                    assert!(
                        !s.map.lanes().is_empty() && !s.map.road_edges().is_empty(),
                        "{}",
                        src.display()
                    );
                }
                n += scenes.len();
            }
            Err(e) => failures.push(e.to_string()),
        }
    }
    assert!(failures.is_empty(), "{failures:#?}");
    assert!(n >= 113, "only {n} scenes found under {}", root.display());
}
