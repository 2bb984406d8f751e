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

/// The subcommands, as `drivescript SUB --help` takes them (`bench io|cost|sample` is one).
const SUBCOMMANDS: [&str; 14] = [
    "inspect",
    "render",
    "convert",
    "cost",
    "test-scripts",
    "stdlib-doc",
    "eval",
    "dataset",
    "train",
    "simulate",
    "demo",
    "ask",
    "prompt show",
    "bench",
];

/// The flags `drivescript SUB --help` lists under "Options:", short and long.
fn help_flags(sub: &str) -> std::collections::BTreeSet<String> {
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
        .args(sub.split(' '))
        .arg("--help")
        .output()
        .expect("the binary runs");
    assert!(out.status.success(), "drivescript {sub} --help failed");
    let text = String::from_utf8(out.stdout).unwrap();
    let mut flags = std::collections::BTreeSet::new();
    let mut options = false;
    for line in text.lines() {
        if line == "Options:" {
            options = true;
        } else if options && !line.is_empty() && !line.starts_with(' ') {
            // The next section (Examples:).
            break;
        } else if options {
            // An option's line is indented 2 (`-o, --output`) or 6 (`--long`) columns; its
            // description, 10.
            let t = line.trim_start();
            if line.len() - t.len() <= 6 && t.starts_with('-') {
                flags.extend(flags_in(t.split(" <").next().unwrap_or(t)));
            }
        }
    }
    assert!(flags.contains("--help"), "{sub}: {text}");
    flags
}

/// The flags a piece of a command line names: `--long` and `-x`, without their values.
fn flags_in(text: &str) -> Vec<String> {
    text.split(|c: char| c.is_whitespace() || "[]|(),".contains(c))
        .filter_map(|t| {
            let name: String = if let Some(long) = t.strip_prefix("--") {
                let n: String = long
                    .chars()
                    .take_while(|c| c.is_ascii_alphanumeric() || *c == '-')
                    .collect();
                (n.starts_with(|c: char| c.is_ascii_alphabetic())).then(|| format!("--{n}"))?
            } else {
                let short = t.strip_prefix('-')?;
                (short.len() == 1 && short.chars().all(|c| c.is_ascii_alphabetic()))
                    .then(|| t.to_string())?
            };
            Some(name)
        })
        .collect()
}

/// The subcommand a code span or command line starts with (`drivescript` dropped), and the
/// rest of it.
fn subcommand_of(text: &str) -> Option<(&'static str, &str)> {
    let t = text.trim();
    let t = t.strip_prefix("drivescript ").unwrap_or(t).trim_start();
    SUBCOMMANDS.iter().find_map(|sub| {
        let rest = t.strip_prefix(sub)?;
        (rest.is_empty() || rest.starts_with(char::is_whitespace)).then_some((*sub, rest))
    })
}

/// Every flag docs/cli.md gives a subcommand is one its `--help` lists: in the synopsis (each
/// `drivescript SUB` line and the lines continuing it), and in the prose, where a flag belongs
/// to the subcommand named in its code span (`simulate --steps`) or to the subcommands named
/// last before it in its paragraph or list item (`train` `--steps`, `simulate` and `ask`
/// `--script-budget`); one named in parentheses applies only there. `demo --steps` was
/// documented, and `demo` has no such flag.
#[test]
fn every_flag_docs_cli_gives_a_subcommand_is_one_it_has() {
    let text = read("docs/cli.md");
    let mut helps = std::collections::BTreeMap::new();
    let mut has = |sub: &str, flag: &str| {
        helps
            .entry(sub.to_string())
            .or_insert_with(|| help_flags(sub))
            .contains(flag)
    };
    let mut wrong = Vec::new();
    let mut checked = 0;
    // The synopsis: the first code block.
    let start = text.find("```\n").expect("the synopsis") + 4;
    let len = text[start..].find("```").expect("its end");
    let (synopsis, prose) = (&text[start..start + len], &text[start + len + 3..]);
    let mut sub = None;
    let mut subs = std::collections::BTreeSet::new();
    for line in synopsis.lines() {
        let line = line.split(" # ").next().unwrap_or(line);
        let rest = if line.starts_with(char::is_whitespace) {
            line
        } else {
            let (s, rest) = subcommand_of(line)
                .unwrap_or_else(|| panic!("docs/cli.md: a synopsis line of no subcommand: {line}"));
            sub = Some(s);
            subs.insert(s);
            rest
        };
        let sub = sub.expect("a synopsis line before its continuation");
        for flag in flags_in(rest) {
            checked += 1;
            if !has(sub, &flag) {
                wrong.push(format!("synopsis: {sub} {flag}"));
            }
        }
    }
    assert_eq!(subs.len(), SUBCOMMANDS.len(), "{subs:?}");
    // The prose: code spans in order, each paragraph and list item on its own.
    let mut subject: Vec<&str> = Vec::new();
    let mut outer: Vec<Vec<&str>> = Vec::new();
    let mut last_was_sub = false;
    let mut rest = prose;
    while let Some(open) = rest.find('`') {
        let between = &rest[..open];
        let after = &rest[open + 1..];
        let close = after.find('`').expect("a code span's end");
        let span = after[..close].replace('\n', " ");
        rest = &after[close + 1..];
        let joined = matches!(between.trim(), "" | "and" | ",");
        for (i, piece) in between.split_inclusive('\n').enumerate() {
            // A blank line or a list item's `- ` starts a new subject.
            if i > 0 && (piece.trim().is_empty() || piece.starts_with("- ")) {
                subject.clear();
                outer.clear();
                last_was_sub = false;
            }
            for c in piece.chars() {
                match c {
                    '(' => outer.push(subject.clone()),
                    ')' => subject = outer.pop().unwrap_or_default(),
                    _ => {}
                }
            }
        }
        if let Some((sub, flags)) = subcommand_of(&span) {
            let flags = flags_in(flags);
            for flag in &flags {
                checked += 1;
                if !has(sub, flag) {
                    wrong.push(format!("`{span}`: {sub} has no {flag}"));
                }
            }
            if flags.is_empty() && last_was_sub && joined {
                subject.push(sub);
            } else {
                subject = vec![sub];
            }
            last_was_sub = flags.is_empty();
        } else {
            last_was_sub = false;
            if span.starts_with('-') {
                for flag in flags_in(&span).into_iter().take(1) {
                    for sub in &subject {
                        checked += 1;
                        if !has(sub, &flag) {
                            wrong.push(format!(
                                "`{span}` (of {}): {sub} has no {flag}",
                                subject.join(", ")
                            ));
                        }
                    }
                }
            }
        }
    }
    assert!(checked >= 150, "only {checked} flags checked");
    assert!(
        wrong.is_empty(),
        "docs/cli.md names flags the subcommands do not have:\n{}",
        wrong.join("\n")
    );
}
