//! Every hand-written script in scripts/ has unit tests with a satisfying and a violating case,
//! and they all pass (the same runner as `drivescript test-scripts`).

use std::path::PathBuf;

use drivescript::cost::script_test::{find_test_files, run_test_file, TestFile};

fn scripts_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("scripts")
}

#[test]
fn every_script_has_satisfying_and_violating_cases() {
    let mut scripts: Vec<PathBuf> = std::fs::read_dir(scripts_dir())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "rhai"))
        .collect();
    scripts.sort();
    assert!(
        scripts.len() >= 14,
        "expected the 14 behaviour scripts, found {}",
        scripts.len()
    );
    for s in scripts {
        let test = s.with_extension("test.yaml");
        let text = std::fs::read_to_string(&test)
            .unwrap_or_else(|_| panic!("{} has no {}", s.display(), test.display()));
        let file: TestFile = serde_yaml::from_str(&text).unwrap();
        let satisfied = file
            .cases
            .iter()
            .any(|c| c.expect.total_below.is_some() || !c.expect.terms_below.is_empty());
        let violated = file
            .cases
            .iter()
            .any(|c| c.expect.total_above.is_some() || !c.expect.terms_above.is_empty());
        assert!(
            satisfied && violated,
            "{}: needs a satisfying and a violating case",
            test.display()
        );
    }
}

#[test]
fn script_unit_tests_pass() {
    let files = find_test_files(&[scripts_dir()]).unwrap();
    let mut failures = Vec::new();
    let mut n = 0;
    for f in files {
        for r in run_test_file(&f).unwrap() {
            n += 1;
            if !r.passed {
                failures.push(format!("{} / {}: {}", r.file, r.case, r.detail));
            }
        }
    }
    assert!(failures.is_empty(), "{}", failures.join("\n"));
    assert!(n >= 28, "only {n} cases ran");
}
