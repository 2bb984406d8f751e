//! The README's promises: its YAML example loads, and CI runs exactly its test command.

use std::path::Path;

fn readme() -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("README.md")).unwrap()
}

#[test]
fn readme_yaml_example_loads() {
    let text = readme();
    let start = text
        .find("<!-- yaml-example -->")
        .expect("the example marker");
    let block = &text[start..];
    let body_start = block.find("```yaml\n").expect("a yaml block") + "```yaml\n".len();
    let body_end = block[body_start..].find("```").expect("the block's end") + body_start;
    let scene =
        drivescript::io::yaml::parse(Path::new("README.md"), &block[body_start..body_end]).unwrap();
    assert_eq!(scene.meta.scenario_id, "merge-demo");
    assert_eq!(scene.agents.len(), 3);
    assert_eq!(scene.map.lanes().len(), 6);
    assert_eq!(scene.map.graph().successors(100), &[200]);
    assert_eq!(scene.map.graph().left(100), Some(101));
    let cyclist = scene.agent(3).unwrap();
    assert_eq!(cyclist.valid_span(), Some((20, 90)));
    // Agent 2 ends in lane 0 after its lane change: closest to lane 100/200/300's centre.
    let last = cyclist.states.len() - 1;
    let car = scene.agent(2).unwrap().states[last];
    let lane = scene.map.lane_at(car.position(), car.heading).unwrap();
    assert_eq!(
        lane % 100,
        0,
        "agent 2 should end in the rightmost lane, got lane {lane}"
    );
}

#[test]
fn ci_runs_the_readme_test_command() {
    let text = readme();
    assert!(text.contains("cargo test --release             # the whole test suite"));
    assert!(text.contains("cargo run --release -- demo"));
    let ci =
        std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join(".ci/run")).unwrap();
    let cmds: Vec<&str> = ci.lines().filter(|l| l.starts_with("cargo ")).collect();
    assert_eq!(cmds, vec!["cargo fmt --check", "cargo test --release"]);
}

#[test]
fn readme_listing_of_the_cut_in_script_is_the_file() {
    let text = readme();
    let head = "`scripts/cut_in.rhai`:\n\n```rhai\n";
    let start = text.find(head).expect("the listing") + head.len();
    let len = text[start..].find("```").expect("its end");
    let file = std::fs::read_to_string(
        std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/cut_in.rhai"),
    )
    .unwrap();
    assert_eq!(&text[start..start + len], file);
}
