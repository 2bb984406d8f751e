//! The README's promises, and those of the docs/ chapters it links: the YAML example loads, the
//! script listings are the files, the tour runs as written, links resolve, and CI runs exactly
//! the README's test command.

mod common;

use std::path::{Path, PathBuf};

fn root() -> &'static Path {
    Path::new(env!("CARGO_MANIFEST_DIR"))
}

fn read(rel: &str) -> String {
    std::fs::read_to_string(root().join(rel)).unwrap_or_else(|e| panic!("{rel}: {e}"))
}

fn readme() -> String {
    read("README.md")
}

/// README.md and every chapter under docs/.
fn documents() -> Vec<PathBuf> {
    let mut out = vec![root().join("README.md")];
    let mut docs: Vec<PathBuf> = std::fs::read_dir(root().join("docs"))
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|x| x == "md"))
        .collect();
    docs.sort();
    assert!(docs.len() >= 8, "{docs:?}");
    out.extend(docs);
    out
}

#[test]
fn yaml_example_loads() {
    let text = read("docs/scene-formats.md");
    let start = text
        .find("<!-- yaml-example -->")
        .expect("the example marker");
    let block = &text[start..];
    let body_start = block.find("```yaml\n").expect("a yaml block") + "```yaml\n".len();
    let body_end = block[body_start..].find("```").expect("the block's end") + body_start;
    let scene = drivescript::io::yaml::parse(
        Path::new("docs/scene-formats.md"),
        &block[body_start..body_end],
    )
    .unwrap();
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
    let ci = read(".ci/run");
    let cmds: Vec<&str> = ci.lines().filter(|l| l.starts_with("cargo ")).collect();
    assert_eq!(cmds, vec!["cargo fmt --check", "cargo test --release"]);
}

#[test]
fn listings_of_the_cut_in_script_are_the_file() {
    let file = read("scripts/cut_in.rhai");
    for doc in ["README.md", "docs/cost-scripts.md"] {
        let text = read(doc);
        let head = "`scripts/cut_in.rhai`:\n\n```rhai\n";
        let start = text
            .find(head)
            .unwrap_or_else(|| panic!("{doc}: the listing"))
            + head.len();
        let len = text[start..].find("```").expect("its end");
        assert_eq!(&text[start..start + len], file, "{doc}");
    }
}

/// The `sh` blocks between `<!-- tour -->` and `<!-- /tour -->`.
fn tour_blocks(text: &str) -> Vec<String> {
    let start = text.find("<!-- tour -->").expect("the tour's start");
    let end = text.find("<!-- /tour -->").expect("the tour's end");
    let mut blocks = Vec::new();
    let mut rest = &text[start..end];
    while let Some(i) = rest.find("```sh\n") {
        let body = &rest[i + "```sh\n".len()..];
        let len = body.find("```").expect("a block's end");
        blocks.push(body[..len].to_string());
        rest = &body[len + 3..];
    }
    blocks
}

/// Every command of the README's five-minute tour runs as written, in order, from a fresh
/// clone (its tracked data, nothing under out/), with no language model configured.
#[test]
fn readme_tour_runs_as_written_from_a_fresh_clone() {
    let blocks = tour_blocks(&readme());
    assert!(blocks.len() >= 5, "{blocks:?}");
    let all = blocks.concat();
    for cmd in [
        "drivescript render",
        "drivescript ask",
        "drivescript cost",
        "drivescript simulate",
        "drivescript eval",
    ] {
        assert!(all.contains(cmd), "the tour lost `{cmd}`");
    }
    let clone = common::fresh_clone();
    for block in &blocks {
        let run = common::bash_in(clone.path(), &["-e"], block);
        assert!(
            run.status.success(),
            "README tour block failed ({:?}):\n{block}\n{}{}",
            run.status.code(),
            String::from_utf8_lossy(&run.stdout),
            String::from_utf8_lossy(&run.stderr)
        );
    }
    assert!(clone.path().join("out/sim").is_dir());
    assert!(clone.path().join("out/ask1/final.rhai").is_file());
}

/// GitHub's anchor for a heading: lower case, punctuation dropped, spaces to hyphens.
fn slug(heading: &str) -> String {
    heading
        .trim()
        .to_lowercase()
        .chars()
        .filter(|c| c.is_alphanumeric() || *c == ' ' || *c == '-' || *c == '_')
        .map(|c| if c == ' ' { '-' } else { c })
        .collect()
}

/// The anchors of a markdown file's headings (outside code blocks).
fn anchors(text: &str) -> Vec<String> {
    let mut fence = false;
    let mut out = Vec::new();
    for line in text.lines() {
        if line.starts_with("```") {
            fence = !fence;
        } else if !fence && line.starts_with('#') {
            let title = line.trim_start_matches('#');
            if title.starts_with(' ') {
                out.push(slug(title));
            }
        }
    }
    out
}

/// Every relative link of the README and of docs/ names a file that exists, and every `#anchor`
/// a heading of its file: nothing points into a section that moved.
#[test]
fn links_between_the_readme_and_docs_resolve() {
    let mut checked = 0;
    for doc in documents() {
        let text = std::fs::read_to_string(&doc).unwrap();
        let dir = doc.parent().unwrap();
        let mut rest = text.as_str();
        while let Some(i) = rest.find("](") {
            let tail = &rest[i + 2..];
            let end = tail.find(')').expect("a link's end");
            let target = &tail[..end];
            rest = &tail[end..];
            if target.starts_with("http://") || target.starts_with("https://") {
                continue;
            }
            let (file, anchor) = match target.split_once('#') {
                Some((f, a)) => (f, Some(a)),
                None => (target, None),
            };
            let path = if file.is_empty() {
                doc.clone()
            } else {
                dir.join(file)
            };
            assert!(
                path.exists(),
                "{}: link to {target}: {} does not exist",
                doc.display(),
                path.display()
            );
            if let Some(a) = anchor {
                let heads = anchors(&std::fs::read_to_string(&path).unwrap());
                assert!(
                    heads.iter().any(|h| h == a),
                    "{}: link to {target}: no heading with anchor #{a} in {} ({heads:?})",
                    doc.display(),
                    path.display()
                );
            }
            checked += 1;
        }
    }
    assert!(checked >= 20, "only {checked} links found");
}

/// The README stays a front page, and every chapter it lists is linked from it.
#[test]
fn readme_is_a_front_page_that_links_every_chapter() {
    let text = readme();
    let lines = text.lines().count();
    assert!(
        lines <= 300,
        "README.md has {lines} lines: move reference into docs/"
    );
    for doc in documents().iter().skip(1) {
        let name = doc.file_name().unwrap().to_str().unwrap();
        assert!(
            text.contains(&format!("](docs/{name})")),
            "README.md does not link docs/{name}"
        );
    }
}
