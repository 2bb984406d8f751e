//! End-to-end tests through the command line, one per scene format, on data/samples.

mod common;

use common::{drivescript, fails, ok, s, samples};
use serde_json::Value;

fn inspect_json(path: &str) -> Vec<Value> {
    let out = ok(&["inspect", path, "--json"]);
    serde_json::from_str::<Value>(&out)
        .unwrap()
        .as_array()
        .unwrap()
        .clone()
}

#[test]
fn inspect_commonroad_2018b_and_2020a() {
    let dir = samples().join("commonroad");
    let all = inspect_json(s(&dir));
    assert_eq!(all.len(), 4);
    let us101 = all
        .iter()
        .find(|v| v["scenario_id"] == "USA_US101-3_3_T-1")
        .unwrap();
    assert_eq!(us101["format"], "commonroad");
    assert_eq!(us101["steps"], 32);
    assert_eq!(us101["agents_by_type"]["vehicle"], 12);
    assert_eq!(us101["lanes"], 12);
    assert_eq!(us101["current_step"], 10);
    // Peachtree is a 2020a-style file with stop lines and line markings.
    let peach = all
        .iter()
        .find(|v| v["scenario_id"] == "USA_Peach-4_8_T-1")
        .unwrap();
    assert!(peach["stop_lines"].as_u64().unwrap() > 0);
    // The validation fold is a hash of the id (`train --val-fold`), fixed across releases.
    assert_eq!(peach["val_fold"], 3);
    assert_eq!(us101["val_fold"], 6);
    assert!(peach["lane_graph"]["successor"].as_u64().unwrap() > 0);
    for v in &all {
        assert!(v["road_edges"].as_u64().unwrap() > 0, "{v}");
        assert_eq!(v["dangling_lane_refs"], 0, "{v}");
    }
}

#[test]
fn inspect_av2_by_directory_and_by_parquet() {
    let dir = samples().join("av2");
    let by_dir = inspect_json(s(&dir));
    assert_eq!(by_dir.len(), 1);
    let v = &by_dir[0];
    assert_eq!(v["format"], "av2");
    assert_eq!(v["scenario_id"], "0a1e6f0a-1817-4a98-b02e-db8c9327d151");
    assert_eq!(v["steps"], 110);
    assert_eq!(v["current_step"], 49);
    assert_eq!(v["agents"], 58);
    assert_eq!(v["ego"], 138951);
    assert_eq!(v["lanes"], 71);
    assert_eq!(v["crosswalks"], 6);
    let parquet = dir.join("scenario_0a1e6f0a-1817-4a98-b02e-db8c9327d151.parquet");
    let by_file = inspect_json(s(&parquet));
    assert_eq!(by_file[0]["agents"], 58);
}

#[test]
fn inspect_yaml_and_text_output() {
    let out = ok(&["inspect", s(&samples().join("yaml/highway_cut_in.yaml"))]);
    assert!(out.contains("highway-cut-in (yaml)"), "{out}");
    assert!(out.contains("4 (4 vehicle), ego 1"), "{out}");
    assert!(out.contains("6 lanes"), "{out}");
}

#[test]
fn inspect_agents_lists_lanes_gaps_and_neighbours() {
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = ok(&[
        "inspect",
        "--agents",
        s(&scene),
        "--max-agents",
        "2",
        "--keep",
        "4",
    ]);
    assert!(out.contains("40 future steps of 0.1 s"), "{out}");
    assert!(out.contains("- vehicle 4:"), "{out}");
    assert!(out.contains("not listed (cap 2)"), "{out}");
    let v: Value =
        serde_json::from_str(&ok(&["inspect", "--agents", "--json", s(&scene)])).unwrap();
    let agents = v[0]["agents"].as_array().unwrap();
    assert_eq!(agents.len(), 4);
    for a in agents {
        assert!(a["lane"].is_i64() && a["speed"].is_f64(), "{a}");
    }
    assert!(v[0]["lanes"].as_array().unwrap().len() >= 2);
    // An id the scene does not hold is a mistake said, not ignored; --keep needs --agents.
    let err = fails(&["inspect", "--agents", s(&scene), "--keep", "4", "77", "88"]);
    assert!(
        err.contains("highway_cut_in.yaml")
            && err.contains("--keep names agents it does not hold: 77, 88"),
        "{err}"
    );
    // A duplicate id was accepted without a word.
    let err = fails(&["inspect", "--agents", s(&scene), "--keep", "4", "2", "4"]);
    assert!(
        err.contains("--keep names agent 4 twice (value 3 of the list)"),
        "{err}"
    );
    // Thousands of absent ids are counted past the first few, not all echoed.
    let ids: Vec<String> = (1000..6000).map(|i| i.to_string()).collect();
    let mut args = vec!["inspect", "--agents", s(&scene), "--keep"];
    args.extend(ids.iter().map(|i| i.as_str()));
    let err = fails(&args);
    assert!(
        err.contains("1009 and 4990 more (5000 in all)") && err.len() < 1000,
        "{err}"
    );
    let o = drivescript(&["inspect", s(&scene), "--keep", "4"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(!o.status.success() && err.contains("--agents"), "{err}");
    // --keep takes every value up to the next flag: a scene after it was read as an agent id,
    // and clap said only "invalid digit found in string".
    let o = drivescript(&["inspect", "--agents", "--keep", "4", s(&scene)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.code() == Some(2)
            && err.contains("not an agent id")
            && err.contains("give the scenes before --keep"),
        "{err}"
    );
    let out = ok(&["inspect", "--agents", "--keep", "4", "--", s(&scene)]);
    assert!(out.contains("- vehicle 4:"), "{out}");
}

#[test]
fn a_scene_after_param_is_named_not_reported_missing() {
    // `cost --param a=1 scene.yaml` read the scene as a parameter and said only that <SCENE>
    // was not given; simulate and eval took it the same way.
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let script = "scripts/cut_in.rhai";
    for cmd in ["cost", "simulate", "eval"] {
        let mut a = vec![cmd];
        if cmd != "eval" {
            a.extend(["--script", script]);
        }
        a.extend(["--param", "cutter=2", s(&scene)]);
        let o = drivescript(&a);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            o.status.code() == Some(2)
                && err.contains("not name=value")
                && err.contains("give the scenes before --param"),
            "{cmd}: {err}"
        );
    }
    let out = ok(&[
        "cost",
        "--script",
        script,
        "--param",
        "cutter=2",
        "victim=1",
        "--",
        s(&scene),
    ]);
    assert!(out.contains("cut_in"), "{out}");
}

#[test]
fn womd_files_written_by_convert_inspect_and_render() {
    let dir = tempfile::tempdir().unwrap();
    let shard = dir.path().join("test.tfrecord-00000-of-00001");
    ok(&[
        "convert",
        s(&samples().join("commonroad/USA_US101-4_1_T-1.xml")),
        "-o",
        s(&shard),
    ]);
    let v = inspect_json(s(&shard));
    assert_eq!(v[0]["format"], "womd");
    assert_eq!(v[0]["scenario_id"], "USA_US101-4_1_T-1");
    assert_eq!(v[0]["agents"], 22);
    assert_eq!(v[0]["steps"], 101);
    // A directory of shards is one source.
    let v = inspect_json(s(dir.path()));
    assert_eq!(v.len(), 1);
    let png = dir.path().join("w.png");
    ok(&["render", s(&shard), "--index", "0", "-o", s(&png)]);
    assert_eq!(&std::fs::read(&png).unwrap()[..4], b"\x89PNG");
    let err = fails(&["render", s(&shard), "--index", "3", "-o", s(&png)]);
    assert!(
        err.contains("--index 3: ") && err.contains("holds 1 scene (give --index 0"),
        "{err}"
    );
}

/// A TFRecord has no drivable areas and no lane boundaries of its own: `convert -o x.tfrecord`
/// of a CommonRoad scene dropped its 12 drivable areas and 12 lanes' boundaries without a
/// word, and the file read back as another map (off-road from road edges only, 3.6 m lanes).
/// Now each part it cannot hold is said; YAML, which holds every part, says nothing.
#[test]
fn convert_says_what_a_tfrecord_cannot_hold() {
    let dir = tempfile::tempdir().unwrap();
    let xml = samples().join("commonroad/USA_US101-3_3_T-1.xml");
    let tf = dir.path().join("us101.tfrecord");
    let out = drivescript(&["convert", s(&xml), "-o", s(&tf)]);
    assert!(out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("us101.tfrecord does not hold 12 drivable area(s): WOMD has none")
            && err.contains("does not hold the boundaries of 12 lane(s)"),
        "{err}"
    );
    assert_eq!(inspect_json(s(&tf))[0]["drivable_areas"], 0);
    // AV2's static objects lose their flag.
    let out = drivescript(&["convert", s(&samples().join("av2")), "-o", s(&tf)]);
    assert!(out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("does not hold which 8 agent(s) are static"),
        "{err}"
    );
    let yaml = dir.path().join("us101.yaml");
    let out = drivescript(&["convert", s(&xml), "-o", s(&yaml)]);
    assert!(out.status.success());
    assert!(
        out.stderr.is_empty(),
        "{}",
        String::from_utf8_lossy(&out.stderr)
    );
}

#[test]
fn render_svg_png_gif() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("commonroad/USA_Lanker-1_1_T-1.xml");
    let svg = dir.path().join("a.svg");
    ok(&["render", s(&scene), "-o", s(&svg)]);
    let text = std::fs::read_to_string(&svg).unwrap();
    assert!(text.starts_with("<svg") && text.contains("<polygon") && text.contains(">1261<"));
    // A named agent is drawn in the highlight colour and labelled with its role.
    let roles = dir.path().join("roles.svg");
    ok(&[
        "render",
        s(&scene),
        "--role",
        "1261=cutter",
        "-o",
        s(&roles),
    ]);
    let text = std::fs::read_to_string(&roles).unwrap();
    assert!(
        text.contains(">1261 cutter<") && text.contains("#d21e3c"),
        "{}",
        &text[..400]
    );
    // Two roles for one agent, the second written with a leading zero, were echoed as
    // `--role 1261=victim`, a value nobody typed.
    let out = drivescript(&[
        "render",
        s(&scene),
        "--role",
        "1261=cutter",
        "--role",
        "01261=victim",
        "-o",
        s(&roles),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.code() == Some(1)
            && err.contains(
                "the role \"victim\" for agent 1261: agent 1261 already has the role \"cutter\""
            )
            && !err.contains("1261=victim"),
        "{err}"
    );
    let out = drivescript(&["render", s(&scene), "--role", "cutter", "-o", s(&roles)]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        out.status.code() == Some(2) && err.contains("expected ID=ROLE"),
        "{err}"
    );
    let png = dir.path().join("a.png");
    ok(&[
        "render",
        s(&scene),
        "--step",
        "0",
        "--width",
        "400",
        "-o",
        s(&png),
    ]);
    let bytes = std::fs::read(&png).unwrap();
    assert_eq!(&bytes[..8], b"\x89PNG\r\n\x1a\n");
    assert_eq!(u32::from_be_bytes(bytes[16..20].try_into().unwrap()), 400);
    let gif = dir.path().join("a.gif");
    ok(&[
        "render",
        s(&samples().join("yaml/curved_two_lanes.yaml")),
        "--width",
        "300",
        "-o",
        s(&gif),
    ]);
    let bytes = std::fs::read(&gif).unwrap();
    assert_eq!(&bytes[..6], b"GIF89a");
    // One frame per step (91 steps), 300 pixels wide.
    let mut dec = gif::DecodeOptions::new().read_info(&bytes[..]).unwrap();
    assert_eq!(dec.width(), 300);
    let mut frames = 0;
    while dec.read_next_frame().unwrap().is_some() {
        frames += 1;
    }
    assert_eq!(frames, 91);
    let err = fails(&["render", s(&scene), "-o", s(&dir.path().join("a.bmp"))]);
    assert!(err.contains("unknown picture format"), "{err}");
    let err = fails(&["render", s(&scene), "--step", "500", "-o", s(&png)]);
    assert!(err.contains("--step 500"), "{err}");
}

#[test]
fn convert_to_yaml_round_trips_every_format() {
    let dir = tempfile::tempdir().unwrap();
    for (k, src) in [
        samples().join("commonroad/USA_Peach-4_8_T-1.xml"),
        samples().join("av2"),
        samples().join("yaml/highway_cut_in.yaml"),
    ]
    .iter()
    .enumerate()
    {
        let yaml = dir.path().join(format!("s{k}.yaml"));
        ok(&["convert", s(src), "-o", s(&yaml)]);
        let a = &inspect_json(s(src))[0];
        let b = &inspect_json(s(&yaml))[0];
        for key in [
            "scenario_id",
            "steps",
            "current_step",
            "agents",
            "agents_by_type",
            "ego",
            "lanes",
            "road_edges",
            "road_lines",
            "crosswalks",
            "stop_lines",
            "drivable_areas",
            "lane_graph",
        ] {
            assert_eq!(
                a[key],
                b[key],
                "{key} differs after converting {}",
                src.display()
            );
        }
        assert_eq!(b["format"], "yaml");
    }
}

/// AV2's static objects (cones, parked things) were written as `static: true` beside their
/// recorded states, and the YAML reader then replaced those states with the first observed
/// pose at every step: 8 objects of the AV2 sample moved, and 5 unobserved for part of the
/// recording were present throughout, so the file read back as another scene without a word.
/// Explicit states are now kept as given; the trajectories of the YAML are the source's.
#[test]
fn explicit_states_of_a_static_agent_read_back_as_written() {
    let dir = tempfile::tempdir().unwrap();
    let yaml = dir.path().join("av2.yaml");
    ok(&["convert", s(&samples().join("av2")), "-o", s(&yaml)]);
    assert!(std::fs::read_to_string(&yaml)
        .unwrap()
        .contains("static: true"));
    let (a, b) = (dir.path().join("a.json"), dir.path().join("b.json"));
    ok(&["convert", s(&samples().join("av2")), "-o", s(&a)]);
    ok(&["convert", s(&yaml), "-o", s(&b)]);
    let agents = |p: &std::path::Path| {
        let v: Value = serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap();
        v["agents"].clone()
    };
    let (a, b) = (agents(&a), agents(&b));
    assert_eq!(a.as_array().unwrap().len(), 58);
    for (x, y) in a.as_array().unwrap().iter().zip(b.as_array().unwrap()) {
        assert_eq!(x, y, "agent {} changed on the way through YAML", x["id"]);
    }
}

#[test]
fn rollout_json_written_and_rendered() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let json = dir.path().join("r.json");
    ok(&["convert", s(&scene), "-o", s(&json)]);
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v["format"], "drivescript-rollout");
    assert_eq!(v["agents"][0]["states"].as_array().unwrap().len(), 91);
    assert_eq!(v["agents"][0]["states"][0].as_array().unwrap().len(), 4);
    let svg = dir.path().join("r.svg");
    ok(&["render", s(&scene), "--rollout", s(&json), "-o", s(&svg)]);
    // A rollout with a wrong version is refused with its field named.
    let bad = std::fs::read_to_string(&json)
        .unwrap()
        .replace("\"version\":1", "\"version\":7");
    std::fs::write(&json, bad).unwrap();
    let err = fails(&["render", s(&scene), "--rollout", s(&json), "-o", s(&svg)]);
    assert!(
        err.contains("r.json: version: unsupported version 7"),
        "{err}"
    );
}

#[test]
fn unknown_formats_list_the_supported_ones() {
    let dir = tempfile::tempdir().unwrap();
    let f = dir.path().join("scene.osm");
    std::fs::write(&f, "<osm/>").unwrap();
    let err = fails(&["inspect", s(&f)]);
    assert!(
        err.contains("scene.osm: unknown scene format") && err.contains("CommonRoad XML"),
        "{err}"
    );
    let err = fails(&["inspect", "no/such/file.xml"]);
    assert!(err.contains("no/such/file.xml"), "{err}");
}

/// The subcommands `drivescript --help` lists (but `help`).
fn subcommands() -> Vec<String> {
    let help = ok(&["--help"]);
    let listing = help
        .split("Commands:\n")
        .nth(1)
        .expect("a command list")
        .split("\n\n")
        .next()
        .unwrap();
    listing
        .lines()
        .filter(|l| l.starts_with("  ") && !l.starts_with("   "))
        .filter_map(|l| l.split_whitespace().next())
        .filter(|c| *c != "help")
        .map(String::from)
        .collect()
}

/// The examples of a `--help` text: shell command lines, with `\\`-continued lines joined.
fn examples(cmd: &str, help: &str) -> Vec<String> {
    let section = help
        .split("Examples:\n")
        .nth(1)
        .unwrap_or_else(|| panic!("{cmd} --help has no examples"));
    let mut out: Vec<String> = Vec::new();
    for line in section.lines().take_while(|l| !l.trim().is_empty()) {
        let continued = out.last().is_some_and(|l| l.ends_with('\\'));
        if line.starts_with("      ") {
            // A line clap wrapped would land here without a `\\` before it.
            assert!(
                continued,
                "{cmd} --help: example wrapped, shorten it: {line:?}"
            );
            let last = out.last_mut().unwrap();
            last.push('\n');
            last.push_str(line);
        } else {
            assert!(
                !continued,
                "{cmd} --help: a `\\` continues nothing before {line:?}"
            );
            let e = line.trim();
            assert!(
                line.starts_with("  ") && (e.starts_with("drivescript ") || e.starts_with('(')),
                "{cmd} --help: not a command (an example wrapped? shorten it): {line:?}"
            );
            out.push(e.to_string());
        }
    }
    assert!(!out.is_empty(), "{cmd} --help has no examples");
    out
}

#[test]
fn every_help_example_runs_as_written_from_a_fresh_clone() {
    let commands = subcommands();
    assert!(commands.len() >= 14, "{commands:?}");
    for cmd in &commands {
        let help = ok(&[cmd, "--help"]);
        // A clone's tracked directories, and nothing it would not have (out/, runs/).
        let clone = common::fresh_clone();
        for e in examples(cmd, &help) {
            assert!(!e.contains("shared/"), "{cmd} --help needs ../shared: {e}");
            let run = common::bash_in(clone.path(), &[], &e);
            assert!(
                run.status.success(),
                "{cmd} --help example failed ({:?}): {e}\n{}{}",
                run.status.code(),
                String::from_utf8_lossy(&run.stdout),
                String::from_utf8_lossy(&run.stderr)
            );
        }
    }
}

#[test]
fn demo_runs_the_loop_and_writes_the_run() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("demo");
    let out = ok(&["demo", "-o", s(&run)]);
    assert!(out.contains("USA_US101-4_1_T-1"), "{out}");
    // Every phase: plan, script, validation, sampling, per-term costs, verdicts and why a
    // sample does not meet the request, the planner's answer. With polish, realism's look at
    // the joint of history and future, held slow headings and the crab term at every speed,
    // three of the first script's four samples meet the request (two before the last two),
    // and the planner accepts the first.
    for want in [
        "round 0: plan:",
        "cut_in (cutter=401 victim=405)",
        "round 0: script (",
        "round 0: validating on the sampler's horizon",
        "| ends_ahead |",
        "round 0: sample 0: meets the request [cut_in PASS, off_road PASS]",
        "round 0: sample 1: meets the request [cut_in PASS, off_road PASS]",
        "round 0: sample 2: 2 reason(s) it does not: term ends_ahead",
        "round 1: ACCEPT (sample 0 of round 0 meets the request)",
        "Outcome: accepted",
        "Verdict: succeeded: round 0 met.",
    ] {
        assert!(out.contains(want), "{want:?} missing:\n{out}");
    }
    let gif = std::fs::read(run.join("final.gif")).unwrap();
    assert_eq!(&gif[..6], b"GIF89a");
    let script = std::fs::read_to_string(run.join("final.rhai")).unwrap();
    assert!(script.contains("agent(401)") && script.contains("agent(389)"));
    let costs: Value = serde_json::from_str(
        &std::fs::read_to_string(run.join("round_0/USA_US101-4_1_T-1_costs.json")).unwrap(),
    )
    .unwrap();
    assert_eq!(costs["checks"][0]["behaviour"], "cut_in");
    assert_eq!(costs["checks"][1]["behaviour"], "off_road");
    // The rollouts are named as `simulate` names them, listed, and scored by the eval command
    // the demo prints for each checker.
    let listed = format!(
        "rollouts of the final round, in {}: round_0/USA_US101-4_1_T-1_0.json … round_0/USA_US101-4_1_T-1_3.json and round_0/USA_US101-4_1_T-1_costs.json",
        run.display()
    );
    assert!(out.contains(&listed), "{listed:?} missing:\n{out}");
    let evals: Vec<&str> = out
        .lines()
        .filter_map(|l| l.trim().strip_prefix("score them: drivescript "))
        .collect();
    assert_eq!(evals.len(), 2, "{out}");
    // Each scores every sample against its unguided twin, with the demo's verdicts.
    for (e, checker) in evals.iter().zip(["cut_in", "off_road"]) {
        let passed = out
            .lines()
            .filter(|l| l.starts_with("round 0: sample "))
            .filter(|l| l.contains(&format!("{checker} PASS")))
            .count();
        let args: Vec<&str> = e.split(' ').collect();
        let table = ok(&args);
        let want = format!("| {checker} | 4 | {:.2} |", passed as f64 / 4.0);
        assert!(table.contains(&want), "{e}: {want:?} missing:\n{table}");
    }
    // Running it again replaces the run instead of refusing.
    ok(&["demo", "-o", s(&run)]);
}

#[test]
fn the_rules_planner_repairs_a_script_whose_samples_fail() {
    // The demo's request without polish: no sample of the first script gets the cutter far
    // enough ahead, and the planner repairs the script.
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("ask");
    let scene = samples().join("commonroad/USA_US101-4_1_T-1.xml");
    let out = ok(&[
        "ask",
        s(&scene),
        "vehicle 401 cuts in front of vehicle 405, vehicle 389 drives off the road",
        "--llm",
        "rules",
        "--polish",
        "0",
        "-o",
        s(&run),
    ]);
    for want in [
        "round 0: sample 0: ",
        "round 1: plan:\n    Repair (rules planner): the best sample fails",
        "Outcome: accepted",
    ] {
        assert!(out.contains(want), "{want:?} missing:\n{out}");
    }
    assert!(
        !out.contains("round 0: sample 0: meets the request"),
        "{out}"
    );
    assert!(run.join("round_1/USA_US101-4_1_T-1_costs.json").exists());
}

#[test]
fn convert_moves_the_current_step() {
    let dir = tempfile::tempdir().unwrap();
    let y = dir.path().join("c30.yaml");
    let src = samples().join("commonroad/USA_US101-4_1_T-1.xml");
    ok(&[
        "convert",
        s(&src),
        "-o",
        s(&y),
        "--current-step",
        "30",
        "--id",
        "us101_c30",
    ]);
    let v = inspect_json(s(&y));
    assert_eq!(v[0]["current_step"], 30);
    assert_eq!(v[0]["scenario_id"], "us101_c30");
    let err = fails(&["convert", s(&src), "-o", s(&y), "--current-step", "100"]);
    assert!(err.contains("leaves no future"), "{err}");
    // The largest step a flag holds: `step + 1` wrapped to 0 (a panic in a debug build), and
    // the error blamed an unobserved step.
    let max = u64::MAX.to_string();
    let err = fails(&["convert", s(&src), "-o", s(&y), "--current-step", &max]);
    assert!(
        err.contains(&format!("current step {max} leaves no future")),
        "{err}"
    );
}

#[test]
fn cost_on_arrays_nested_deep_ends_without_overflowing_the_stack() {
    // Rhai compares and prints nested arrays recursively, up to 2 KB of stack a level: the
    // main thread's 8 MB overflowed at 5,000 levels (a second of `a = [a]`) and the process
    // aborted, exit 134, "stack overflow".
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let dir = tempfile::tempdir().unwrap();
    let deep = dir.path().join("deep.rhai");
    std::fs::write(
        &deep,
        "let a = [];\nfor i in 0..6000 { a = [a]; }\nlet b = a == a;\nlet c = [a].contains(a);\n\
         term(\"t\", agent(1).x.mean());\n",
    )
    .unwrap();
    let out = drivescript(&["cost", s(&scene), "--script", s(&deep)]);
    let text = format!(
        "{}{}",
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr)
    );
    assert!(
        out.status.success() || text.contains("limit exceeded: wall time"),
        "{:?}: {text}",
        out.status
    );
}

#[test]
fn cost_prints_terms_and_gradients() {
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = ok(&[
        "cost",
        s(&scene),
        "--script",
        "scripts/cut_in.rhai",
        "--param",
        "cutter=2",
        "victim=1",
    ]);
    assert!(
        out.contains("ends_in_victim_lane") && out.contains("evaluated in"),
        "{out}"
    );
    let out = ok(&[
        "cost",
        s(&scene),
        "--script",
        "scripts/rightmost_lane.rhai",
        "--param",
        "vehicle=3",
        "--json",
    ]);
    let v: Value = serde_json::from_str(&out).unwrap();
    assert!(v["total"].as_f64().unwrap() > 1.0, "{v}");
    assert_eq!(v["agent_grad_norms"][0]["agent"], 3);
    // On the sampler's horizon: a script valid on the 80 recorded steps indexes past 40.
    let dir = tempfile::tempdir().unwrap();
    let late = dir.path().join("late.rhai");
    std::fs::write(&late, "term(\"late\", agent(1).x.at(60));\n").unwrap();
    let out = ok(&["cost", s(&scene), "--script", s(&late)]);
    assert!(out.contains("80 steps"), "{out}");
    let err = fails(&["cost", s(&scene), "--script", s(&late), "--horizon", "40"]);
    assert!(err.contains("late.rhai:1"), "{err}");
    let out = ok(&[
        "cost",
        s(&scene),
        "--script",
        "scripts/cut_in.rhai",
        "--param",
        "cutter=2",
        "victim=1",
        "--horizon",
        "40",
    ]);
    assert!(out.contains("40 steps"), "{out}");
    // A rollout as the candidate, and errors with the script's line.
    let dir = tempfile::tempdir().unwrap();
    let json = dir.path().join("r.json");
    ok(&["convert", s(&scene), "-o", s(&json)]);
    ok(&[
        "cost",
        s(&scene),
        "--script",
        "scripts/cut_in.rhai",
        "--param",
        "cutter=2",
        "victim=1",
        "--rollout",
        s(&json),
    ]);
    let bad = dir.path().join("bad.rhai");
    std::fs::write(&bad, "let a = agent(1);\nterm(\"t\", a.x);\n").unwrap();
    let err = fails(&["cost", s(&scene), "--script", s(&bad)]);
    assert!(
        err.contains("bad.rhai:2:1") && err.contains("not a Series"),
        "{err}"
    );
    let o = drivescript(&[
        "cost",
        s(&scene),
        "--script",
        "scripts/cut_in.rhai",
        "--param",
        "cutter",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(
        o.status.code() == Some(2) && err.contains("'cutter'") && err.contains("not name=value"),
        "{err}"
    );
}

#[test]
fn test_scripts_runs_the_suite_and_fails_on_a_broken_expectation() {
    let out = ok(&["test-scripts", "scripts/cut_in.test.yaml"]);
    assert!(out.contains("3 passed, 0 failed"), "{out}");
    let text = failing_case("speed_limit.rhai", "vehicle: 1", "total_above: 100.0");
    assert!(
        text.contains("FAILED total > 100") && text.contains("0 passed, 1 failed"),
        "{text}"
    );
}

#[test]
fn stdlib_doc_is_markdown_of_every_section() {
    let out = ok(&["stdlib-doc"]);
    for s in [
        "# drivescript cost-script reference",
        "## Agents",
        "`a.lane_path() -> Path`",
        "## Terms",
        "Module `behaviours`",
    ] {
        assert!(out.contains(s), "missing {s}");
    }
}

#[test]
fn eval_prints_tables_for_baselines_and_rollouts() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = samples().join("commonroad");
    let json = dir.path().join("e.json");
    let out = ok(&[
        "eval",
        s(&scenes),
        "--task",
        "conditional",
        "--json",
        s(&json),
    ]);
    assert!(out.contains("| log replay | 4 | 0.00 | 0.00 |"), "{out}");
    assert!(out.contains("| constant velocity | 4 |"), "{out}");
    // The samples hold two highway maps (US 101) and two with junctions (Lankershim,
    // Peachtree), all vehicles: rows per map kind, none per agent type.
    assert!(out.contains("| log replay | highway | 2 | 0.00 |"), "{out}");
    assert!(out.contains("| constant velocity | urban | 2 |"), "{out}");
    assert!(!out.contains("| vehicles |"), "{out}");
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    assert_eq!(v["methods"][0]["summary"]["jsd"]["mean"], 0.0);
    assert!(v["methods"][1]["summary"]["ade"].as_f64().unwrap() > 0.1);
    let groups = v["groups"].as_array().unwrap();
    assert_eq!(groups.len(), 2 * 3, "{groups:?}");
    assert_eq!(groups[0]["group"], "highway");
    assert_eq!(groups[0]["scenes"], 2);
    let maps: Vec<&str> = v["methods"][0]["scenes"]
        .as_array()
        .unwrap()
        .iter()
        .map(|r| r["map"].as_str().unwrap())
        .collect();
    assert_eq!(
        maps.iter().filter(|m| **m == "urban").count(),
        2,
        "{maps:?}"
    );
    // Rollouts written by anyone are scored: here the recorded futures, so ADE is 0.
    let rolls = dir.path().join("rollouts");
    std::fs::create_dir(&rolls).unwrap();
    for name in ["USA_US101-3_3_T-1", "USA_Peach-4_8_T-1"] {
        let src = scenes.join(format!("{name}.xml"));
        ok(&[
            "convert",
            s(&src),
            "-o",
            s(&rolls.join(format!("{name}.json"))),
        ]);
    }
    let pair = dir.path().join("pair");
    std::fs::create_dir(&pair).unwrap();
    for name in ["USA_US101-3_3_T-1", "USA_Peach-4_8_T-1"] {
        std::fs::copy(
            scenes.join(format!("{name}.xml")),
            pair.join(format!("{name}.xml")),
        )
        .unwrap();
    }
    let out = ok(&[
        "eval",
        s(&pair),
        "--task",
        "conditional",
        "--rollouts",
        s(&rolls),
    ]);
    assert!(out.contains("| 2 | 0.00 | 0.00 |"), "{out}");
    let out = ok(&[
        "eval",
        s(&pair),
        "--task",
        "unconditional",
        "--baseline",
        "cv",
    ]);
    assert!(out.contains("| constant velocity | 2 |"), "{out}");
    let out = ok(&[
        "eval",
        s(&samples().join("yaml/highway_cut_in.yaml")),
        "--task",
        "behaviour",
        "--behaviour",
        "cut_in",
        "--param",
        "cutter=2",
        "victim=1",
        "--baseline",
        "log",
    ]);
    assert!(out.contains("| log replay | cut_in | 1 | 1.00 |"), "{out}");
    // Words are checker parameters too, as the loop passes them (as recorded, the turning car
    // crosses first: the yield is not met).
    let junction = [
        "eval",
        "scripts/scenes/junction.yaml",
        "--task",
        "behaviour",
    ];
    let yield_args = ["--behaviour", "yield", "--param", "yielder=1", "other=2"];
    let log = ["--baseline", "log"];
    let out = ok(&[&junction[..], &yield_args, &["yielder_turn=left"], &log].concat());
    assert!(out.contains("| log replay | yield | 1 | 0.00 |"), "{out}");
    let err = fails(&[&junction[..], &yield_args, &["yielder_turn=sideways"], &log].concat());
    assert!(
        err.contains("\"yielder_turn\" = \"sideways\" must be \"straight\", \"left\" or \"right\""),
        "{err}"
    );
    let err = fails(&[
        "eval",
        s(&pair),
        "--task",
        "behaviour",
        "--behaviour",
        "dance",
    ]);
    assert!(err.contains("unknown behaviour \"dance\""), "{err}");
    // Agents chosen per scene: vehicle 1 (the ego, middle lane) for a left lane change.
    let out = ok(&[
        "eval",
        "scripts/scenes",
        "--task",
        "behaviour",
        "--behaviour",
        "lane_change_left",
        "--auto",
        "--baseline",
        "log",
    ]);
    assert!(
        out.contains("| log replay | lane_change_left | 6 | 0.17 |"),
        "{out}"
    );
}

/// The off-road figure of the rollouts row of a conditional `eval` table.
#[test]
fn eval_shows_a_rollouts_directory_s_name_on_one_line_and_merge_reads_it_back() {
    // The name starts a row of the table: a line break in the directory's name split the row
    // (here into a fake one) and an escape sequence reached the terminal as it was.
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("commonroad/USA_US101-3_3_T-1.xml");
    let rolls = dir.path().join("r\n| fake | 9 |\u{1b}[2J");
    std::fs::create_dir(&rolls).unwrap();
    ok(&[
        "convert",
        s(&scene),
        "-o",
        s(&rolls.join("USA_US101-3_3_T-1.json")),
    ]);
    let json = dir.path().join("e.json");
    let out = ok(&[
        "eval",
        s(&scene),
        "--task",
        "conditional",
        "--rollouts",
        s(&rolls),
        "--json",
        s(&json),
    ]);
    assert!(
        !out.contains('\u{1b}') && !out.lines().any(|l| l.starts_with("| fake")),
        "{out}"
    );
    assert!(
        out.contains("r\\u{000A}| fake | 9 |\\u{001B}[2J | 1 |"),
        "{out}"
    );
    let merged = ok(&["eval", "--merge", s(&json)]);
    assert!(
        merged.contains("r\\u{000A}| fake | 9 |\\u{001B}[2J | 1 |"),
        "{merged}"
    );
}

fn rollouts_offroad(out: &str) -> f64 {
    let row = out
        .lines()
        .find(|l| l.starts_with("| rollouts in"))
        .unwrap_or_else(|| panic!("no rollouts row: {out}"));
    let cells: Vec<&str> = row.split('|').map(str::trim).collect();
    cells[cells.len() - 3].parse().unwrap()
}

#[test]
fn eval_scores_every_method_over_the_same_steps() {
    // The recording of car 363 stops at step 20; a rollout drives it (and, from step 25, car
    // 376) 50 m off the road.
    let dir = tempfile::tempdir().unwrap();
    let src = samples().join("commonroad/USA_US101-3_3_T-1.xml");
    let yaml = dir.path().join("scene/USA_US101-3_3_T-1.yaml");
    std::fs::create_dir(yaml.parent().unwrap()).unwrap();
    ok(&["convert", s(&src), "-o", s(&yaml)]);
    let rolls = dir.path().join("rollouts");
    std::fs::create_dir(&rolls).unwrap();
    let rollout = rolls.join("USA_US101-3_3_T-1.json");
    ok(&["convert", s(&yaml), "-o", s(&rollout)]);
    let mut doc: serde_yaml::Value =
        serde_yaml::from_str(&std::fs::read_to_string(&yaml).unwrap()).unwrap();
    let states = doc["agents"][0]["states"].as_sequence_mut().unwrap();
    assert_eq!(states.len(), 32);
    for st in &mut states[21..] {
        *st = serde_yaml::Value::Null;
    }
    std::fs::write(&yaml, serde_yaml::to_string(&doc).unwrap()).unwrap();
    let mut r: Value = serde_json::from_str(&std::fs::read_to_string(&rollout).unwrap()).unwrap();
    for (agent, from) in [(0, 21), (1, 25)] {
        for st in r["agents"][agent]["states"].as_array_mut().unwrap()[from..].iter_mut() {
            st[1] = (st[1].as_f64().unwrap() + 50.0).into();
        }
    }
    std::fs::write(&rollout, r.to_string()).unwrap();
    let eval = |extra: &[&str]| {
        let mut a = vec![
            "eval",
            s(&yaml),
            "--task",
            "conditional",
            "--rollouts",
            s(&rolls),
        ];
        a.extend_from_slice(extra);
        rollouts_offroad(&ok(&a))
    };
    let n = 12.0_f64;
    assert_eq!(eval(&[]), (1.0 / n * 1e3).round() / 1e3, "car 376 only");
    assert_eq!(
        eval(&["--all-steps"]),
        (2.0 / n * 1e3).round() / 1e3,
        "both cars"
    );
    assert_eq!(
        eval(&["--horizon", "10", "--all-steps"]),
        0.0,
        "the rollout is cut to the 10 steps the baselines simulate"
    );
}

#[test]
fn eval_scores_rollouts_over_their_own_horizon_by_default() {
    // Car 4 rear-ends car 2 at 3.9 s. The recording holds 3 s, the rollout (a model's 40
    // steps) 4 s: the accident used to read as a miss unless --horizon was given.
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("scripts/scenes/highway.yaml"))
        .unwrap()
        .replace(
            "{id: 4, lane: 0, s: 20, speed: 18}",
            "{id: 4, lane: 0, s: 40, speed: 30.5}\n  - {id: 5, type: cyclist, lane: 2, s: 200, speed: 6}",
        );
    let scene = dir.path().join("highway.yaml");
    std::fs::write(&scene, text.replace("steps: 81", "steps: 41")).unwrap();
    let long = dir.path().join("long.yaml");
    std::fs::write(&long, text.replace("steps: 81", "steps: 51")).unwrap();
    let rollouts = dir.path().join("r");
    std::fs::create_dir(&rollouts).unwrap();
    ok(&["convert", s(&long), "-o", s(&rollouts.join("highway.json"))]);
    let eval = |extra: &[&str]| {
        let mut a = vec![
            "eval",
            s(&scene),
            "--task",
            "behaviour",
            "--behaviour",
            "accident",
            "--param",
            "attacker=4",
            "target=2",
            "--rollouts",
            s(&rollouts),
            "--baseline",
            "log",
        ];
        a.extend_from_slice(extra);
        ok(&a)
    };
    let out = eval(&[]);
    assert!(
        out.contains("| rollouts in ") && out.contains("| accident | 1 | 1.00 | 1.00 |"),
        "{out}"
    );
    // The log is scored over the same 40 steps (unobserved after its 30).
    assert!(
        out.contains("| log replay | accident | 1 | 0.00 | 0.00 |"),
        "{out}"
    );
    assert!(
        out.contains("horizon (future steps scored after the current step): 40 steps, the rollouts' own (1 scene)"),
        "{out}"
    );
    // A verdict is the scene's: the rows of one agent type have none (they read 0 before).
    assert!(
        out.contains("| log replay | vehicles | accident | - | - | - |")
            && out.contains("| log replay | cyclists | accident | - | - | - |"),
        "{out}"
    );
    // With a cyclist scored, the implausible legend speaks of road users and the cyclist's
    // own limits (it said "fraction of vehicles ... a car cannot drive" under cyclist rows).
    assert!(
        out.contains("implausible: fraction of road users")
            && out.contains("cyclists above 15 m/s or beyond 5 m/s², turning tighter than 0.5 1/m")
            && !out.contains("fraction of vehicles (pooled over scenes and samples)"),
        "{out}"
    );
    // Once, though cyclists are scored both as a whole and within their map kind (they were
    // named twice).
    assert_eq!(out.matches("cyclists above 15 m/s").count(), 1, "{out}");
    // An explicit horizon still rules, and is said.
    let out = eval(&["--horizon", "30"]);
    assert!(
        !out.contains("| accident | 1 | 1.00 |") && out.contains("30 steps, --horizon (1 scene)"),
        "{out}"
    );
    // Without rollouts, the recorded future.
    let out = ok(&[
        "eval",
        s(&scene),
        "--task",
        "behaviour",
        "--behaviour",
        "accident",
        "--param",
        "attacker=4",
        "target=2",
        "--baseline",
        "log",
    ]);
    assert!(
        out.contains("30 steps, the recorded future (1 scene)"),
        "{out}"
    );
}

/// `simulate SCENE --checkpoint CKPT EXTRA... -o OUT`.
fn simulate_args<'a>(
    scene: &'a str,
    ckpt: &'a str,
    extra: &[&'a str],
    out: &'a str,
) -> Vec<&'a str> {
    let mut v = vec!["simulate", scene, "--checkpoint", ckpt];
    v.extend_from_slice(extra);
    v.extend(["-o", out]);
    v
}

#[test]
fn simulate_takes_a_script_reading_a_parameter_as_a_constant() {
    // Parameters are constants (`cutter` for `--param cutter=2`, docs/cost-scripts.md); the
    // syntax check simulate runs before any scene had none, and refused the script:
    // "Undefined variable: cutter".
    let dir = tempfile::tempdir().unwrap();
    let script = dir.path().join("p.rhai");
    std::fs::write(&script, "term(\"x\", agent(cutter).speed.mean());\n").unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join("sim");
    ok(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &[
            "--script",
            s(&script),
            "--param",
            "cutter=2",
            "--steps",
            "8",
            "--horizon",
            "5",
        ],
        s(&out),
    ));
}

#[test]
fn simulate_says_that_a_script_prints_and_where_to_see_it() {
    // `print` shows under `cost`; under `simulate` its lines were dropped without a word.
    let dir = tempfile::tempdir().unwrap();
    let script = dir.path().join("p.rhai");
    std::fs::write(
        &script,
        "print(\"speed\");\nterm(\"x\", agent(2).speed.mean());\n",
    )
    .unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join("sim");
    let o = drivescript(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &["--script", s(&script), "--steps", "8", "--horizon", "5"],
        s(&out),
    ));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("p.rhai prints: sampling does not show what it prints; `drivescript cost` on the scene with this script does"),
        "{err}"
    );
}

#[test]
fn a_slow_script_stops_at_the_run_s_script_budget_instead_of_running_for_minutes() {
    let dir = tempfile::tempdir().unwrap();
    // Tens of milliseconds per evaluation, within the per-call limit: the run's hundreds of
    // evaluations (32 Heun steps, 2 x 300 polish iterations, 4 samples) would take minutes.
    let script = dir.path().join("slow.rhai");
    std::fs::write(
        &script,
        "let n = 0; for i in 0..200000 { n += 1; }\nlet a = agent(1);\n\
         term(\"far\", square(a.x.last() - 1000.0));\n",
    )
    .unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join("out");
    let t0 = std::time::Instant::now();
    let o = drivescript(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &[
            "--script",
            s(&script),
            "--samples",
            "4",
            "--script-budget",
            "0.5",
        ],
        s(&out),
    ));
    let t = format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    );
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("the cost scripts took")
            && t.contains(" evaluations (")
            && t.contains("s each), past this run's budget of 0.5 s")
            && t.contains("--script-budget"),
        "{t}"
    );
    assert!(t0.elapsed().as_secs() < 60, "{:?}: {t}", t0.elapsed());
    let err = fails(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &["--script", s(&script), "--script-budget", "0"],
        s(&out),
    ));
    assert!(
        err.contains("--script-budget 0: must be more than 0"),
        "{err}"
    );
}

#[test]
fn the_yield_example_holds_at_a_merge() {
    // The worked example the LLM is shown: with a 2 m margin from the centres (inside both
    // boxes) and no route term, the sampler moved the ramp car 2-12 m off its lane beside the
    // main-lane car where the lanes merge, instead of holding it back.
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let example = std::fs::read_to_string(root.join("prompts/examples/yield.md")).unwrap();
    let script = example
        .split("```rhai\n")
        .nth(1)
        .and_then(|rest| rest.split("```").next())
        .expect("a rhai block")
        .replace("agent(5)", "agent(11)")
        .replace("agent(6)", "agent(10)");
    let rhai = dir.path().join("yield.rhai");
    std::fs::write(&rhai, script).unwrap();
    // The merge of scripts/scenes with the ramp car (11) first at the meeting point, 0.3 s
    // before the main-lane car (10), at their recorded speeds.
    let scene = dir.path().join("merge.yaml");
    let text = std::fs::read_to_string(root.join("scripts/scenes/merge_ramp_first.yaml"))
        .unwrap()
        .replace(
            "{id: 10, route: [1, 3], s: 50, speed: 15}",
            "{id: 10, route: [1, 3], s: 112.5, speed: 15}",
        )
        .replace(
            "{id: 11, route: [2, 3], s: 30, speed: 21}",
            "{id: 11, route: [2, 3], s: 117.84, speed: 16}",
        );
    assert!(text.contains("s: 117.84"));
    std::fs::write(&scene, text).unwrap();
    let out = dir.path().join("out");
    ok(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &[
            "--task",
            "unconditional",
            "--script",
            s(&rhai),
            "--samples",
            "2",
        ],
        s(&out),
    ));
    let json = dir.path().join("eval.json");
    ok(&[
        "eval",
        s(&scene),
        "--task",
        "behaviour",
        "--behaviour",
        "yield",
        "--param",
        "yielder=11",
        "other=10",
        "--rollouts",
        s(&out),
        "--samples",
        "2",
        "--json",
        s(&json),
    ]);
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let verdicts = v["methods"][0]["scenes"][0]["verdicts"].as_array().unwrap();
    assert_eq!(verdicts.len(), 2);
    for verdict in verdicts {
        let m = &verdict["measured"];
        assert!(
            verdict["passed"] == true && m["yielder_off_route_m"].as_f64().unwrap() <= 2.0,
            "{verdict}"
        );
        // The main-lane car passes the meeting point within the horizon, before the yielder.
        let (other, yielder) = (
            m["other_passes_s"].as_f64().unwrap(),
            m["yielder_reaches_s"].as_f64().unwrap(),
        );
        assert!(
            other > 0.0 && (yielder < 0.0 || yielder > other),
            "{verdict}"
        );
    }
}

/// `train --export E --cache E` cut every window of the corpus into E, then refused E as "not
/// empty" (its own cache) and left the windows there; a cache inside the export directory did
/// the same. Both are refused before any scene is read, naming both flags.
#[test]
fn train_export_refuses_a_cache_in_or_around_the_export_directory() {
    let dir = tempfile::tempdir().unwrap();
    let exp = dir.path().join("exp");
    for (cache, says) in [
        (exp.clone(), "is the export directory (--export)"),
        (
            exp.join("windows"),
            "is inside the export directory (--export)",
        ),
        (
            dir.path().to_path_buf(),
            "holds the export directory (--export)",
        ),
    ] {
        let err = fails(&[
            "train",
            "--data",
            "scripts/scenes",
            "--export",
            s(&exp),
            "--cache",
            s(&cache),
            "--resume",
            "data/checkpoint",
        ]);
        assert!(
            err.contains("the window cache (--cache)")
                && err.contains(says)
                && !err.contains("exporting into"),
            "{err}"
        );
        assert!(!exp.exists(), "{err}");
    }
}

/// `train --resume CK --steps N` with N no more than CK's steps read the whole corpus and cut
/// its windows into the cache before saying "the checkpoint has already done ... steps".
#[test]
fn a_resumed_run_with_no_steps_left_is_refused_before_the_windows_are_cut() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let err = fails(&[
        "train",
        "--data",
        "scripts/scenes",
        "--resume",
        "data/checkpoint",
        "--out",
        s(&out),
        "--steps",
        "5000",
    ]);
    assert!(
        err.contains("the checkpoint has already done 10000 steps"),
        "{err}"
    );
    assert!(!out.exists(), "{err}");
}

/// A scene whose steps are not 0.1 s apart (`dt: 0.5`) was sampled by the 10 Hz model as if
/// each step took 0.1 s (futures five times too slow) and trained on the same way, exit 0.
/// Sampling, training and `dataset` refuse it naming the file, the scene and its step.
#[test]
fn a_scene_of_another_time_step_is_refused_by_sampling_and_training() {
    let dir = tempfile::tempdir().unwrap();
    let corpus = dir.path().join("corpus");
    std::fs::create_dir(&corpus).unwrap();
    let text = std::fs::read_to_string("scripts/scenes/highway_cut_in.yaml").unwrap();
    let scene = corpus.join("slow.yaml");
    std::fs::write(&scene, text.replacen("steps: 81", "dt: 0.5\nsteps: 81", 1)).unwrap();
    let says = |err: &str| {
        assert!(
            err.contains("slow.yaml: scene highway-cut-in: its steps are 0.5 s apart")
                && err.contains("0.1 s (10 Hz)"),
            "{err}"
        );
    };
    let out = dir.path().join("out");
    says(&fails(&[
        "simulate",
        s(&scene),
        "--checkpoint",
        "data/checkpoint",
        "-o",
        s(&out),
    ]));
    assert!(!out.join("highway-cut-in_0.json").exists());
    let ckpt = dir.path().join("ckpt");
    says(&fails(&[
        "train",
        "--data",
        s(&corpus),
        "--out",
        s(&ckpt),
        "--steps",
        "2",
    ]));
    assert!(!ckpt.join("model.safetensors").exists());
    says(&fails(&["dataset", s(&corpus)]));
}

/// `train --out X --cache X` trained and wrote its checkpoint among the windows; the same
/// command resumed (`--resume X`) was then refused, the cache holding files not its own. A
/// cache that is, or holds, the checkpoint directory is refused before the windows are cut.
#[test]
fn a_window_cache_that_is_or_holds_the_checkpoint_directory_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    for (cache, says) in [
        (out.clone(), "is the"),
        (dir.path().to_path_buf(), "holds the"),
    ] {
        let err = fails(&[
            "train",
            "--data",
            "scripts/scenes",
            "--out",
            s(&out),
            "--cache",
            s(&cache),
            "--steps",
            "2",
        ]);
        assert!(
            err.contains(&format!(
                "the window cache (--cache) {says} checkpoint directory (--out)"
            )),
            "{err}"
        );
        assert!(!out.exists(), "{err}");
    }
}

#[test]
fn train_export_writes_the_windows_of_a_checkpoint_into_a_new_directory_only() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = dir.path().join("ckpt");
    ok(&[
        "train",
        "--data",
        "scripts/scenes",
        "--out",
        s(&ckpt),
        "--steps",
        "2",
        "--batch",
        "2",
        "--eval-every",
        "2",
    ]);
    let exp = dir.path().join("exp");
    let out = ok(&[
        "train",
        "--data",
        "scripts/scenes",
        "--export",
        s(&exp),
        "--resume",
        s(&ckpt),
    ]);
    assert!(
        out.contains("training and") && out.contains("files to"),
        "{out}"
    );
    for f in [
        "train-00000.safetensors",
        "check.safetensors",
        "basis.safetensors",
        "config.json",
    ] {
        assert!(exp.join(f).is_file(), "{f}: {out}");
    }
    let before = std::fs::read(exp.join("check.safetensors")).unwrap();
    let err = fails(&[
        "train",
        "--data",
        "scripts/scenes",
        "--export",
        s(&exp),
        "--resume",
        s(&ckpt),
    ]);
    // Refused before the windows are cut, not after ("exporting into ...").
    assert!(
        err.contains("is not empty") && !err.contains("exporting into"),
        "{err}"
    );
    assert_eq!(
        std::fs::read(exp.join("check.safetensors")).unwrap(),
        before
    );
    // Said of --export, the flag given, not of --out.
    for (target, says) in [
        ("scripts/scenes/x", "is inside the input directory"),
        ("scripts/cut_in.rhai", "is not a directory"),
    ] {
        let err = fails(&[
            "train",
            "--data",
            "scripts/scenes",
            "--export",
            target,
            "--resume",
            s(&ckpt),
        ]);
        assert!(
            err.contains("the export directory (--export)")
                && err.contains(says)
                && !err.contains("--out"),
            "{err}"
        );
    }
    // The windows are encoded for a checkpoint's network: without one there is nothing to
    // encode them for; and an export writes no checkpoint.
    // A resumed run keeps its inputs.
    let resumed = |flag: &[&str]| {
        let ckpt = s(&ckpt);
        fails(
            &[
                &[
                    "train",
                    "--data",
                    "scripts/scenes",
                    "--out",
                    ckpt,
                    "--resume",
                    ckpt,
                    "--steps",
                    "4",
                ],
                flag,
            ]
            .concat(),
        )
    };
    let err = resumed(&["--nearest-lane-pose"]);
    assert!(err.contains("without the lanes' nearest points"), "{err}");
    let err = resumed(&["--goals"]);
    assert!(
        err.contains("--goals: ") && err.contains("was trained without agents' end points"),
        "{err}"
    );
    // And its training noise levels; a new run's are checked before any data is read.
    let err = resumed(&["--p-mean=-0.4"]);
    assert!(
        err.contains("--p-mean -0.4: ")
            && err.contains("drew its noise levels with p_mean -1.2; a resumed run keeps them"),
        "{err}"
    );
    // And its loss.
    let err = resumed(&["--across-weight", "10"]);
    assert!(
        err.contains("--across-weight 10: ")
            && err
                .contains("weighs the error across the path 1 times; a resumed run keeps its loss"),
        "{err}"
    );
    let err = fails(&[
        "train",
        "--data",
        "scripts/scenes",
        "--out",
        s(&dir.path().join("fresh")),
        "--p-std",
        "0",
    ]);
    assert!(
        err.contains("--p-std: edm.p_std = 0: must be positive"),
        "{err}"
    );
    let usage = |args: &[&str]| {
        let out = drivescript(args);
        assert_eq!(out.status.code(), Some(2), "{args:?}");
        String::from_utf8_lossy(&out.stderr).into_owned()
    };
    let err = usage(&["train", "--data", "scripts/scenes", "--export", s(&exp)]);
    assert!(err.contains("--resume"), "{err}");
    let err = usage(&[
        "train",
        "--data",
        "scripts/scenes",
        "--export",
        s(&exp),
        "--resume",
        s(&ckpt),
        "--out",
        s(&ckpt),
    ]);
    assert!(err.contains("--out"), "{err}");
}

#[test]
fn a_resumed_run_refuses_another_seed_or_setting_and_keeps_another_run_s_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let tiny = |out: &std::path::Path, seed: &str| {
        ok(&[
            "train",
            "--data",
            "scripts/scenes",
            "--out",
            s(out),
            "--steps",
            "2",
            "--batch",
            "2",
            "--eval-every",
            "2",
            "--seed",
            seed,
        ])
    };
    let (a, b) = (dir.path().join("a"), dir.path().join("b"));
    tiny(&a, "1");
    tiny(&b, "9");
    let weights = |d: &std::path::Path| std::fs::read(d.join("model.safetensors")).unwrap();
    let before = weights(&b);
    // Resuming a into b replaced b's own checkpoint with a's continuation, exit 0.
    let more = |out: &std::path::Path, from: &std::path::Path, extra: &[&str]| {
        let mut args = vec![
            "train",
            "--data",
            "scripts/scenes",
            "--out",
            s(out),
            "--resume",
            s(from),
            "--steps",
            "4",
            "--batch",
            "2",
            "--eval-every",
            "2",
        ];
        args.extend_from_slice(extra);
        fails(&args)
    };
    let err = more(&b, &a, &[]);
    assert!(
        err.contains("already holds a checkpoint")
            && err.contains("--resume continues another one")
            && err.contains("--force"),
        "{err}"
    );
    assert_eq!(weights(&b), before);
    // The seed and the setting of a resumed run were its checkpoint's, whatever was given.
    let err = more(&a, &a, &["--seed", "77"]);
    assert!(
        err.contains("--seed 77: ") && err.contains("trained with seed 1"),
        "{err}"
    );
    let err = more(&a, &a, &["--setting", "cities"]);
    assert!(
        err.contains("--setting: ") && err.contains("40-step futures without"),
        "{err}"
    );
    // Said as the flag spells it, not as Rust's `Common`.
    let err = more(&a, &a, &["--component-scale", "capped"]);
    assert!(
        err.contains("scales its PCA components as `--component-scale common`")
            && !err.contains("Common"),
        "{err}"
    );
    // The checkpoint's own seed and setting, given again, are no change.
    ok(&[
        "train",
        "--data",
        "scripts/scenes",
        "--out",
        s(&a),
        "--resume",
        s(&a),
        "--steps",
        "4",
        "--batch",
        "2",
        "--eval-every",
        "2",
        "--seed",
        "1",
        "--setting",
        "ngsim",
    ]);
    // A truncated optimiser state was "invalid header length", candle's words.
    let opt = a.join("optimizer.safetensors");
    let bytes = std::fs::read(&opt).unwrap();
    std::fs::write(&opt, &bytes[..1000]).unwrap();
    let err = more(&a, &a, &[]);
    assert!(
        err.contains("optimizer.safetensors: the header says it is")
            && err.contains("but the file is 1000 bytes: not a safetensors file, or cut short"),
        "{err}"
    );
    std::fs::write(&opt, &bytes).unwrap();
    // A config edited to a fold no scene hashes to validated on nothing without a word.
    let cfg = a.join("config.json");
    let mut v: Value = serde_json::from_str(&std::fs::read_to_string(&cfg).unwrap()).unwrap();
    v["config"]["val_fold"] = 11.into();
    std::fs::write(&cfg, v.to_string()).unwrap();
    let err = more(&a, &a, &[]);
    assert!(
        err.contains("config.val_fold = 11: must be 0 to 9"),
        "{err}"
    );
    // A cache named as a checkpoint file became a directory there, and the checkpoint could
    // not be saved after the whole run: "Is a directory".
    let c = dir.path().join("c");
    let cache = c.join("model.safetensors");
    let err = fails(&[
        "train",
        "--data",
        "scripts/scenes",
        "--out",
        s(&c),
        "--cache",
        s(&cache),
        "--steps",
        "2",
        "--batch",
        "2",
        "--eval-every",
        "2",
    ]);
    assert!(
        err.contains("is where the checkpoint in") && err.contains("writes its model.safetensors"),
        "{err}"
    );
    assert!(!cache.exists());
    // A damaged config of the checkpoint resumed in place says where it is not JSON.
    let text = std::fs::read_to_string(&cfg).unwrap().replacen(
        "\"ema_half_life\":0.0",
        "\"ema_half_life\":NaN",
        1,
    );
    assert!(text.contains("NaN"), "{text}");
    std::fs::write(&cfg, text).unwrap();
    let err = more(&a, &a, &[]);
    assert!(
        err.contains("which is not a checkpoint's config (line 1, column"),
        "{err}"
    );
}

#[test]
fn eval_merge_refuses_samples_which_the_shards_record() {
    // Every other flag of a single run was refused beside --merge; --samples 3 was ignored and
    // the shards merged as they were (issue 32). Refused before any file is read.
    let out = drivescript(&["eval", "--merge", "a.json", "b.json", "--samples", "3"]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(
        err.contains("--merge") && err.contains("--samples") && err.contains("cannot be used"),
        "{err}"
    );
}

#[test]
fn eval_merge_refuses_shards_of_evaluations_of_different_scenes() {
    // Shard 0/2 of one scene and shard 1/2 of another merged into one table, exit 0: the
    // shards' settings agreed and nothing recorded what they had read.
    let dir = tempfile::tempdir().unwrap();
    let shard = |scene: &str, i: usize, name: &str| {
        let out = dir.path().join(name);
        let run = drivescript(&[
            "eval",
            s(&samples().join(scene)),
            "--task",
            "conditional",
            "--baseline",
            "cv",
            "--shard",
            &format!("{i}/2"),
            "--json",
            s(&out),
        ]);
        assert!(out.exists(), "{name}");
        (out, run)
    };
    let us101 = "commonroad/USA_US101-3_3_T-1.xml";
    let peach = "commonroad/USA_Peach-4_8_T-1.xml";
    let (a, _) = shard(us101, 0, "a.json");
    // The other shard holds no scene: it says so and exits 0, as `simulate --shard` does (it
    // said "nothing was scored: no scene ... was read from the given paths", exit 1).
    let (b, empty) = shard(us101, 1, "b.json");
    let said = String::from_utf8_lossy(&empty.stdout);
    assert!(
        empty.status.success() && said.contains("shard 1/2 holds none of the 1 scenes"),
        "{said}{}",
        String::from_utf8_lossy(&empty.stderr)
    );
    let (other, _) = shard(peach, 1, "other.json");
    ok(&["eval", "--merge", s(&a), s(&b)]);
    let err = fails(&["eval", "--merge", s(&a), s(&other)]);
    assert!(
        err.contains("shards of evaluations of different scenes") && err.contains("other.json"),
        "{err}"
    );
    // A key named twice was read as its last copy without a word.
    let text = std::fs::read_to_string(&a).unwrap();
    let at = text.find('{').unwrap() + 1;
    let twice = dir.path().join("twice.json");
    std::fs::write(
        &twice,
        format!("{}\"groups\": [],{}", &text[..at], &text[at..]),
    )
    .unwrap();
    let err = fails(&["eval", "--merge", s(&twice), s(&b)]);
    assert!(
        err.contains("twice.json") && err.contains("the key \"groups\" twice"),
        "{err}"
    );
}

#[test]
fn test_scripts_given_a_cost_script_says_so() {
    // A .rhai read as a test file said "line 1, column 1: unknown field `// Follow`, expected
    // `script` or `cases`" (issue 32).
    let err = fails(&["test-scripts", "scripts/follow.rhai"]);
    assert!(
        err.contains("scripts/follow.rhai: is a cost script, not a test file")
            && err.contains("scripts/follow.test.yaml")
            && !err.contains("unknown field"),
        "{err}"
    );
}

#[test]
fn eval_refuses_a_baseline_named_twice() {
    // `--baseline cv --baseline cv` scored it twice: two identical rows of one method (issue 32).
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let err = fails(&[
        "eval",
        "--task",
        "conditional",
        "--baseline",
        "cv",
        "--baseline",
        "lane",
        "--baseline",
        "cv",
        s(&scene),
    ]);
    assert!(err.contains("--baseline cv: given twice"), "{err}");
}

#[test]
fn render_refuses_a_step_for_a_gif_which_draws_every_step() {
    // `render -o x.gif --step 3` wrote the whole animation, byte for byte the one without
    // --step, and said nothing of the step (issue 32).
    let dir = tempfile::tempdir().unwrap();
    let gif = dir.path().join("x.gif");
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let err = fails(&["render", "-o", s(&gif), "--step", "3", s(&scene)]);
    assert!(
        err.contains("step 3: a GIF draws every step") && err.contains("as PNG or SVG"),
        "{err}"
    );
    assert!(!gif.exists());
    // One step is drawn as PNG; the animation without --step.
    ok(&[
        "render",
        "-o",
        s(&dir.path().join("x.png")),
        "--step",
        "3",
        s(&scene),
    ]);
    ok(&["render", "-o", s(&gif), s(&scene)]);
}

#[test]
fn train_export_refuses_the_training_flags_it_would_ignore() {
    // An export cuts and holds out windows as the --resume checkpoint's config says and trains
    // nothing: `--val-fold 3` exported fold 0's split without a word, and --steps, --lr,
    // --nearest-lane-pose and the rest were dropped the same way (issue 32). Refused before
    // anything is read, so neither the checkpoint nor the directory need exist.
    let dir = tempfile::tempdir().unwrap();
    let (exp, ckpt) = (dir.path().join("exp"), dir.path().join("ckpt"));
    for flag in [
        &["--val-fold", "3"][..],
        &["--val-town", "DEU_Flensburg"],
        &["--steps", "7"],
        &["--batch", "3"],
        &["--lr", "0.5"],
        &["--seed", "4"],
        &["--eval-every", "2"],
        &["--ema-half-life", "5"],
        &["--component-scale", "capped"],
        &["--scale-cap", "0.5"],
        &["--p-mean=-0.4"],
        &["--p-std", "2"],
        &["--nearest-lane-pose"],
        &["--goals"],
        &["--force"],
        &["--setting", "cities"],
    ] {
        let mut args = vec![
            "train",
            "--data",
            "scripts/scenes",
            "--export",
            s(&exp),
            "--resume",
            s(&ckpt),
        ];
        args.extend_from_slice(flag);
        let out = drivescript(&args);
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{flag:?}: {err}");
        let name = flag[0].split('=').next().unwrap();
        assert!(
            err.contains("--export") && err.contains(name) && err.contains("cannot be used"),
            "{flag:?}: {err}"
        );
        assert!(!exp.exists(), "{flag:?}");
    }
}

#[test]
fn a_model_that_reads_end_points_simulates_both_tasks_and_is_not_exported() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = dir.path().join("ckpt");
    let ck = s(&ckpt);
    ok(&[
        "train",
        "--data",
        "scripts/scenes",
        "--out",
        ck,
        "--steps",
        "2",
        "--batch",
        "2",
        "--eval-every",
        "2",
        "--goals",
    ]);
    let config: Value =
        serde_json::from_str(&std::fs::read_to_string(ckpt.join("config.json")).unwrap()).unwrap();
    assert_eq!(config["config"]["window"]["goals"], true);
    assert_eq!(config["config"]["model"]["goals"], true);
    for task in ["conditional", "unconditional"] {
        let out = dir.path().join(task);
        ok(&[
            "simulate",
            "scripts/scenes/highway.yaml",
            "--checkpoint",
            ck,
            "--task",
            task,
            "--samples",
            "1",
            "--steps",
            "8",
            "-o",
            s(&out),
        ]);
        assert!(out.join("highway_0.json").exists(), "{task}");
    }
    let err = fails(&[
        "train",
        "--data",
        "scripts/scenes",
        "--export",
        s(&dir.path().join("exp")),
        "--resume",
        ck,
    ]);
    assert!(
        err.contains("reads agents' end points (window.goals)")
            && err.contains("nothing to export to"),
        "{err}"
    );
}

#[test]
fn train_then_simulate_end_to_end() {
    let dir = tempfile::tempdir().unwrap();
    let ckpt = dir.path().join("ckpt");
    let out = ok(&[
        "train",
        "--data",
        "scripts/scenes",
        "--out",
        s(&ckpt),
        "--steps",
        "4",
        "--batch",
        "2",
        "--eval-every",
        "2",
        "--val-fold",
        "3",
    ]);
    assert!(out.contains("trained 4 steps"), "{out}");
    // A line per checkpoint even though the progress bar is hidden (no terminal here).
    assert!(
        out.contains("step      2  train") && out.contains("step      4  train"),
        "{out}"
    );
    assert!(ckpt.join("model.safetensors").exists() && ckpt.join("config.json").exists());
    // Fold 3 of the script scenes is the cut-in scene alone (`inspect` prints each fold).
    let config: Value =
        serde_json::from_str(&std::fs::read_to_string(ckpt.join("config.json")).unwrap()).unwrap();
    assert_eq!(config["config"]["val_fold"], 3);
    assert_eq!(config["val_scenes"], serde_json::json!(["highway-cut-in"]));
    // Every file of the checkpoint has one mode, and no temporary file is left.
    #[cfg(unix)]
    {
        use std::os::unix::fs::PermissionsExt;
        for f in ["model.safetensors", "config.json", "optimizer.safetensors"] {
            let mode = std::fs::metadata(ckpt.join(f))
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o777, 0o644, "{f}");
        }
    }
    let names: Vec<String> = std::fs::read_dir(&ckpt)
        .unwrap()
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    assert!(names.iter().all(|n| !n.ends_with(".tmp")), "{names:?}");
    // Training from scratch over it is refused without --force.
    let before = std::fs::read(ckpt.join("model.safetensors")).unwrap();
    let err = fails(&[
        "train",
        "--data",
        "scripts/scenes",
        "--out",
        s(&ckpt),
        "--steps",
        "2",
    ]);
    assert!(
        err.contains("already holds a checkpoint") && err.contains("--force"),
        "{err}"
    );
    assert_eq!(
        std::fs::read(ckpt.join("model.safetensors")).unwrap(),
        before
    );
    let ck = s(&ckpt);
    // `train --resume` of the checkpoint, with these arguments.
    let resume = |more: &[&'static str]| {
        let mut v = vec![
            "train",
            "--data",
            "scripts/scenes",
            "--out",
            ck,
            "--resume",
            ck,
        ];
        v.extend_from_slice(more);
        v
    };
    let err = fails(&resume(&["--steps", "6", "--val-fold", "2"]));
    assert!(err.contains("held out fold 3"), "{err}");
    // --steps is a total: resuming a 4-step checkpoint to 6 runs two more steps.
    let out = ok(&resume(&[
        "--steps",
        "6",
        "--batch",
        "2",
        "--eval-every",
        "2",
    ]));
    assert!(
        out.contains("resuming from") && out.contains("trained 6 steps"),
        "{out}"
    );
    let err = fails(&resume(&["--steps", "3"]));
    assert!(err.contains("already done 6 steps"), "{err}");
    // --auto picks the agents and the script for each scene.
    let cut_in_scene = samples().join("yaml/highway_cut_in.yaml");
    let cut_in = s(&cut_in_scene);
    let auto = dir.path().join("auto");
    let out = ok(&simulate_args(
        cut_in,
        s(&ckpt),
        &["--auto", "cut_in", "--steps", "8"],
        s(&auto),
    ));
    assert!(
        out.contains("highway-cut-in: cutter=") && out.contains("ends_in_victim_lane"),
        "{out}"
    );
    let err = fails(&simulate_args(
        cut_in,
        s(&ckpt),
        &["--auto", "cut_inn"],
        s(&auto),
    ));
    assert!(
        err.contains("unknown behaviour") && err.contains("cut_in"),
        "{err}"
    );
    let sim = dir.path().join("sim");
    let out = ok(&simulate_args(
        cut_in,
        s(&ckpt),
        &[
            "--script",
            "scripts/cut_in.rhai",
            "--param",
            "cutter=2",
            "victim=1",
            "--samples",
            "2",
            "--steps",
            "8",
        ],
        s(&sim),
    ));
    assert!(
        out.contains("ends_in_victim_lane") && out.contains("2 samples"),
        "{out}"
    );
    for f in [
        "highway-cut-in_0.json",
        "highway-cut-in_1.json",
        "highway-cut-in_0.gif",
        "highway-cut-in_costs.json",
    ] {
        assert!(sim.join(f).exists(), "{f} missing");
    }
    // The rollouts are scored like anyone else's.
    let r: Value =
        serde_json::from_str(&std::fs::read_to_string(sim.join("highway-cut-in_0.json")).unwrap())
            .unwrap();
    assert_eq!(r["format"], "drivescript-rollout");
    let out = ok(&[
        "eval",
        cut_in,
        "--task",
        "behaviour",
        "--behaviour",
        "cut_in",
        "--param",
        "cutter=2",
        "victim=1",
        "--rollouts",
        s(&sim),
        "--samples",
        "2",
    ]);
    // Both samples are judged.
    assert!(out.contains("| cut_in | 2 |"), "{out}");
    // ... and costed over the model's horizon, however long the recording is.
    let rollout = sim.join("highway-cut-in_0.json");
    let out = ok(&[
        "cost",
        cut_in,
        "--script",
        "scripts/cut_in.rhai",
        "--param",
        "cutter=2",
        "victim=1",
        "--rollout",
        s(&rollout),
    ]);
    let horizon = r["agents"][0]["states"].as_array().unwrap().len() - 1 - 10;
    assert!(
        out.contains(&format!("(rollout future, {horizon} steps)")),
        "{out}"
    );
    // A scene that fails (no vehicle 4 on the merge) is reported, and the others go on.
    let two = dir.path().join("two");
    std::fs::create_dir(&two).unwrap();
    for f in ["highway_cut_in.yaml", "merge.yaml"] {
        std::fs::copy(format!("scripts/scenes/{f}"), two.join(f)).unwrap();
    }
    let partial = dir.path().join("partial");
    let no_vehicle_4 = [
        "--script",
        "scripts/cut_in.rhai",
        "--param",
        "cutter=4",
        "victim=1",
        "--steps",
        "8",
    ];
    let err = fails(&simulate_args(
        s(&two),
        s(&ckpt),
        &no_vehicle_4,
        s(&partial),
    ));
    assert!(
        err.contains("error: merge") && err.contains("1 scenes failed"),
        "{err}"
    );
    assert!(partial.join("highway-cut-in_0.json").exists());
    // When every scene fails, nothing claims to be written.
    let none = dir.path().join("none");
    let out = drivescript(&simulate_args(
        s(&two.join("merge.yaml")),
        s(&ckpt),
        &no_vehicle_4,
        s(&none),
    ));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1));
    assert!(
        stdout.contains("no scene simulated: nothing written") && !stdout.contains("wrote"),
        "{stdout}"
    );
    // A scene that fails after writing its rollouts (a directory where its picture goes)
    // left them, and the run said "nothing written".
    let late = dir.path().join("late");
    std::fs::create_dir_all(late.join("highway-cut-in_0.gif")).unwrap();
    let out = drivescript(&simulate_args(cut_in, s(&ckpt), &[], s(&late)));
    let stdout = String::from_utf8_lossy(&out.stdout);
    assert_eq!(out.status.code(), Some(1));
    assert!(late.join("highway-cut-in_0.json").exists());
    assert!(
        !stdout.contains("nothing written")
            && stdout.contains("no scene simulated to the end")
            && stdout.contains("left some of them in"),
        "{stdout}"
    );
    // Closed loop re-plans every 0.5 s over the model's 4 s horizon.
    let cl = dir.path().join("cl");
    let out = ok(&simulate_args(
        cut_in,
        s(&ckpt),
        &["--closed-loop", "--steps", "8"],
        s(&cl),
    ));
    assert!(out.contains("highway-cut-in: 1 samples"), "{out}");
    let err = fails(&simulate_args(
        cut_in,
        s(&dir.path().join("nope")),
        &[],
        s(&sim),
    ));
    assert!(err.contains("nope: no such checkpoint directory"), "{err}");
}

#[test]
fn simulate_says_what_it_does_not_sample() {
    // The AV2 sample records 6 s after its current step and holds pedestrians and other
    // objects, which the NGSIM model has never seen (their motion is checked in
    // sample::guided's tests), and one static object, which holds its pose.
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("av2/scenario_0a1e6f0a-1817-4a98-b02e-db8c9327d151.parquet");
    for (task, what) in [
        ("unconditional", "keep their current velocity"),
        ("conditional", "follow their log"),
    ] {
        let out_dir = dir.path().join(task);
        let out = ok(&simulate_args(
            s(&scene),
            "data/checkpoint",
            &["--task", task, "--steps", "8"],
            s(&out_dir),
        ));
        assert!(
            out.contains("samples 4.0 s (40 steps)")
                && out.contains("records 6.0 s (60 steps): the rest is not simulated")
                && out
                    .contains("horizon: 40 steps sampled; 0 of the scenes recorded fewer, 1 more"),
            "{out}"
        );
        assert!(
            out.contains(&format!("are not sampled: they {what}"))
                && out.contains("pedestrian 139397")
                && out.contains("7 agents in 1 scene were not sampled"),
            "{out}"
        );
        assert_eq!(
            out.matches("note: the model has seen only vehicles")
                .count(),
            1
        );
    }
}

#[test]
fn output_into_a_closed_pipe_ends_quietly() {
    // `drivescript ... | head`: the reader goes away before the output is written. println!
    // panicked there (exit 101); a command-line tool ends on SIGPIPE like cat or grep.
    use std::process::{Command, Stdio};
    let mut child = Command::new(env!("CARGO_BIN_EXE_drivescript"))
        .arg("stdlib-doc")
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap();
    drop(child.stdout.take());
    let out = child.wait_with_output().unwrap();
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(!err.contains("panicked"), "{err}");
    assert_ne!(out.status.code(), Some(101), "{err}");
}

#[test]
fn output_onto_a_full_disk_is_an_error_not_a_crash() {
    // /dev/full answers every write with ENOSPC, as a full disk does.
    let Ok(full) = std::fs::OpenOptions::new().write(true).open("/dev/full") else {
        eprintln!("skipped: no /dev/full here");
        return;
    };
    let scene = samples().join("yaml/highway_cut_in.yaml");
    for args in [
        vec!["stdlib-doc"],
        vec!["inspect", s(&scene)],
        vec!["eval", s(&scene), "--task", "conditional"],
    ] {
        let out = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
            .args(&args)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .stdout(full.try_clone().unwrap())
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {err}");
        assert!(
            err.contains("error: cannot write the output to standard output: No space left"),
            "{args:?}: {err}"
        );
        assert!(!err.contains("panicked"), "{args:?}: {err}");
    }
    // With stderr full too, nothing can be said: still exit 1, not an abort.
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
        .arg("stdlib-doc")
        .stdout(full.try_clone().unwrap())
        .stderr(full)
        .output()
        .unwrap();
    assert_eq!(out.status.code(), Some(1));
}

#[test]
fn train_keeps_its_window_cache_out_of_the_inputs_and_out_of_other_directories() {
    // `--cache DATA` wrote train.windows and val.windows among the scenes, exit 0.
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir(&data).unwrap();
    std::fs::copy("scripts/scenes/highway_cut_in.yaml", data.join("a.yaml")).unwrap();
    let mine = dir.path().join("mine");
    std::fs::create_dir(&mine).unwrap();
    std::fs::write(mine.join("thesis.tex"), "mine").unwrap();
    let out = dir.path().join("ckpt");
    let train = |cache: &std::path::Path| {
        fails(&[
            "train",
            "--data",
            s(&data),
            "--out",
            s(&out),
            "--cache",
            s(cache),
            "--steps",
            "1",
        ])
    };
    let err = train(&data);
    assert!(err.contains("is the input directory"), "{err}");
    let err = train(&data.join("windows"));
    assert!(err.contains("is inside the input directory"), "{err}");
    let err = train(&mine);
    assert!(
        err.contains("thesis.tex, which is not one of its files (train.windows, val.windows)"),
        "{err}"
    );
    assert_eq!(std::fs::read_dir(&data).unwrap().count(), 1);
    assert_eq!(std::fs::read_dir(&mine).unwrap().count(), 1);
    assert!(!out.exists());
}

#[test]
fn train_writes_its_checkpoint_outside_the_inputs() {
    // `--out DATA/ckpt --cache ELSEWHERE` trained and wrote model.safetensors and config.json
    // among the scenes, exit 0; a later `train --data DATA` read them as scenes.
    let dir = tempfile::tempdir().unwrap();
    let data = dir.path().join("data");
    std::fs::create_dir(&data).unwrap();
    std::fs::copy("scripts/scenes/highway_cut_in.yaml", data.join("a.yaml")).unwrap();
    let cache = dir.path().join("cache");
    for (corpus, out, cache, want) in [
        (
            "--data",
            data.join("ckpt"),
            Some(&cache),
            "is inside the input directory",
        ),
        (
            "--urban",
            data.clone(),
            Some(&cache),
            "is the input directory",
        ),
        // Without --cache, the cache's default (OUT/windows) is not what the error names.
        (
            "--data",
            data.join("a/../ckpt"),
            None,
            "is inside the input directory",
        ),
    ] {
        let mut args = vec!["train", corpus, s(&data), "--out", s(&out), "--steps", "1"];
        if let Some(c) = cache {
            args.extend(["--cache", s(c)]);
        }
        let err = fails(&args);
        assert!(
            err.contains(&format!(
                "{}: the checkpoint directory (--out) {want} {}",
                out.display(),
                data.display()
            )) && err.contains("choose a directory outside it"),
            "{err}"
        );
        assert!(!err.contains("window cache"), "{err}");
    }
    assert_eq!(std::fs::read_dir(&data).unwrap().count(), 1);
    assert!(!cache.exists());
}

#[test]
fn train_says_why_it_has_no_window_to_train_on() {
    // Both were told "no scene is long enough for 51 steps": an empty folder, and scenes
    // every one of which is held out for validation.
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let out = dir.path().join("ckpt");
    let err = fails(&[
        "train",
        "--data",
        s(&empty),
        "--out",
        s(&out),
        "--steps",
        "1",
    ]);
    assert!(
        err.contains(&format!(
            "{}: no scene file in it (supported: ",
            empty.display()
        )),
        "{err}"
    );
    let data = dir.path().join("data");
    std::fs::create_dir(&data).unwrap();
    std::fs::copy("scripts/scenes/highway_cut_in.yaml", data.join("a.yaml")).unwrap();
    let err = fails(&[
        "train",
        "--urban",
        s(&data),
        "--val-town",
        "highway",
        "--out",
        s(&out),
        "--steps",
        "1",
    ]);
    assert!(
        err.contains("every scene long enough for ")
            && err.contains(
                " steps (1) is held out for validation: validate on fewer towns or add scenes"
            ),
        "{err}"
    );
    assert!(!out.join("model.safetensors").exists());
}

#[test]
fn train_refuses_settings_it_cannot_train_with_before_reading_data() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ckpt");
    for (flag, value, want) in [
        ("--lr", "nan", "lr = NaN: must be positive and finite"),
        ("--lr", "inf", "lr = inf: must be positive and finite"),
        ("--lr", "-1", "lr = -1: must be positive and finite"),
        ("--steps", "0", "steps = 0: must be 1 to"),
        ("--batch", "0", "batch = 0: must be 1 to 4096"),
        (
            "--batch",
            "1000000000",
            "batch = 1000000000: must be 1 to 4096",
        ),
        ("--eval-every", "0", "eval_every = 0: must be at least 1"),
        // Allowed alone, 4096 windows of the setting's sizes asked 290 GB for one step and
        // aborted on allocation (exit 134) or took the machine's memory.
        (
            "--batch",
            "4096",
            "batch = 4096: 4096 windows × 262144 numbers a layer for each",
        ),
        (
            "--batch",
            "257",
            "at most 256 windows a batch with these sizes",
        ),
        // It said "window.route_times = 41", naming no flag.
        (
            "--route-times",
            "41",
            "window.route_times = 41: must be 0 to 40",
        ),
        (
            "--across-weight",
            "0.5",
            "across_weight = 0.5: must be 1 (the plain error) to 1000",
        ),
    ] {
        // A data directory that does not exist: the settings are refused first.
        let arg = format!("{flag}={value}");
        let err = fails(&["train", "--data", "no/such/dir", "--out", s(&out), &arg]);
        assert!(
            err.contains(&format!("training settings: {flag}: ")) && err.contains(want),
            "{flag} {value}: {err}"
        );
        assert!(!out.exists(), "{flag} {value} wrote {}", out.display());
    }
}

#[test]
fn a_sample_batch_too_large_for_memory_is_refused_saying_how_many_samples_fit() {
    // 120 vehicles on a six-lane road: many windows of 24 agents. 1024 samples of 300 asked
    // 38 GB for one batch and aborted on allocation (exit 134) or took the machine's memory.
    let dir = tempfile::tempdir().unwrap();
    let scene = common::crowd_scene(dir.path());
    let out = dir.path().join("sim");
    let started = std::time::Instant::now();
    let err = fails(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &[
            "--task",
            "unconditional",
            "--samples",
            "1024",
            "--steps",
            "8",
        ],
        s(&out),
    ));
    assert!(
        err.contains("samples = 1024: the scene takes")
            && err.contains("past the 1073741824 one sampling run holds")
            && err.contains("samples of this scene fit"),
        "{err}"
    );
    assert!(
        started.elapsed().as_secs() < 30,
        "refused only after {:?}",
        started.elapsed()
    );
    let fit: usize = err
        .split("at most ")
        .nth(1)
        .and_then(|t| t.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("no count: {err}"));
    assert!((1..1024).contains(&fit), "{err}");
}

#[test]
fn sampler_flags_are_checked_before_any_work() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("sim");
    let scene = samples().join("yaml/highway_cut_in.yaml");
    // Ranges fixed in advance are clap's: a usage error naming the flag and its range.
    for (arg, want) in [
        ("--steps=0", "'--steps <STEPS>': 0 is not in 2..=1000"),
        ("--steps=1", "'--steps <STEPS>': 1 is not in 2..=1000"),
        ("--samples=0", "'--samples <SAMPLES>': 0 is not in 1..=1024"),
        (
            "--samples=100000000",
            "'--samples <SAMPLES>': 100000000 is not in 1..=1024",
        ),
    ] {
        let run = drivescript(&simulate_args(
            s(&scene),
            "data/checkpoint",
            &["--task", "unconditional", arg],
            s(&out),
        ));
        let err = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(2), "{arg}: {err}");
        assert!(err.contains(want), "{arg}: {err}");
        assert!(!out.exists(), "{arg} created {}", out.display());
    }
    for (arg, want) in [
        // The schedule's last Heun step from σ = 0.47 left every vehicle at tens of metres a
        // second (at 2 steps, kilometres); a closed loop then failed on an "implausible
        // heading 10262.9 rad".
        (
            "--steps=4",
            "--steps 4: fewer than 8 Heun steps leave noise in the samples",
        ),
        ("--steps=7", "use 8 or more (default 32)"),
        ("--lambda=-1", "--lambda -1: must be 0 to 1000"),
        // 1e308 ran into "non-finite denoiser output", and --realism 1e308 printed weights
        // of 309 digits, neither naming the flag.
        ("--lambda=1e308", "--lambda 1e308: must be 0 to 1000"),
        ("--realism=1e308", "--realism 1e308: must be 0 to 1000"),
        ("--realism=-0.5", "--realism -0.5: must be 0 to 1000"),
        ("--known-weight=-2", "--known-weight -2: must be 0 to 1000"),
        (
            "--known-weight=nan",
            "--known-weight NaN: must be 0 to 1000",
        ),
        (
            "--script-budget=1e-300",
            "--script-budget 1e-300: must be more than 0",
        ),
        // Without a script, once dropped without a word.
        (
            "--param=cutter=2",
            "parameter \"cutter\": no script reads it",
        ),
    ] {
        let err = fails(&simulate_args(
            s(&scene),
            "data/checkpoint",
            &["--task", "unconditional", arg],
            s(&out),
        ));
        assert!(err.contains(want), "{arg}: {err}");
        assert!(!out.exists(), "{arg} created {}", out.display());
    }
    let err = fails(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &["--closed-loop", "--steps", "2"],
        s(&out),
    ));
    assert!(
        err.contains("--steps 2: fewer than 8 Heun steps") && !err.contains("heading"),
        "{err}"
    );
    // Weights with nothing to weigh were dropped without a word.
    for (arg, want) in [
        ("--lambda=10", "--lambda 10: no script to weigh"),
        (
            "--known-weight=5",
            "--known-weight 5: only --task conditional knows end points",
        ),
    ] {
        let err = fails(&simulate_args(
            s(&scene),
            "data/checkpoint",
            &["--task", "unconditional", arg],
            s(&out),
        ));
        assert!(err.contains(want), "{arg}: {err}");
        assert!(!out.exists());
    }
    // The same script twice (once through ./) counted its terms twice, without a word; a
    // checkpoint named as a file read as "config.json/config.json: Not a directory".
    let twice = fails(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &[
            "--script",
            "scripts/cut_in.rhai",
            "--script",
            "./scripts/cut_in.rhai",
            "--param",
            "cutter=2",
            "victim=1",
        ],
        s(&out),
    ));
    assert!(
        twice.contains(
            "--script ./scripts/cut_in.rhai: the same file as --script scripts/cut_in.rhai"
        ),
        "{twice}"
    );
    let file = fails(&simulate_args(
        s(&scene),
        "data/checkpoint/config.json",
        &[],
        s(&out),
    ));
    assert!(
        file.contains("data/checkpoint/config.json: is a file, not a checkpoint directory")
            && !file.contains("config.json/config.json"),
        "{file}"
    );
    assert!(!out.exists());
    // The demo checks its settings before it clears the previous run away.
    let demo = dir.path().join("demo");
    std::fs::create_dir(&demo).unwrap();
    std::fs::write(demo.join("state.json"), "{}").unwrap();
    let run = drivescript(&["demo", "--samples", "0", "-o", s(&demo)]);
    let err = String::from_utf8_lossy(&run.stderr);
    assert_eq!(run.status.code(), Some(2), "{err}");
    assert!(
        err.contains("'--samples <SAMPLES>': 0 is not in 1..=1024"),
        "{err}"
    );
    assert_eq!(
        std::fs::read_to_string(demo.join("state.json")).unwrap(),
        "{}",
        "the previous run was cleared"
    );
    assert!(!demo.join("round_0").exists());
    let err = fails(&["eval", s(&scene), "--task", "conditional", "--samples", "0"]);
    assert!(err.contains("--samples 0: must be 1 to 1024"), "{err}");
    for h in ["0", "100000000"] {
        let err = fails(&["eval", s(&scene), "--task", "conditional", "--horizon", h]);
        assert!(
            err.contains(&format!("--horizon {h}: must be 1 to 10000 steps")),
            "{err}"
        );
    }
    // 1e308 panicked converting to a Duration; -1 and NaN ran with the floor of 0.05 s.
    for sec in ["1e308", "-1", "NaN", "0"] {
        let err = fails(&["bench", "io", "--seconds", sec]);
        assert!(
            err.contains("give 0.05 to 3600 seconds per row"),
            "{sec}: {err}"
        );
    }
}

#[test]
fn dataset_window_flags_are_checked() {
    // --history 0 and --future 0 panicked; --stride 0 behaved like 1.
    for (arg, want) in [
        ("--history=0", "--history: history = 0: must be 1 to 100"),
        ("--future=0", "--future: future = 0: must be 1 to 1000"),
        ("--stride=0", "--stride: stride = 0: must be 1 to 100000"),
    ] {
        let err = fails(&["dataset", "scripts/scenes", arg]);
        assert!(err.contains(want), "{arg}: {err}");
    }
    // No scene there is 100 s long: the PCA table cannot be made, and that was exit 0.
    let err = fails(&["dataset", "scripts/scenes", "--future=1000"]);
    assert!(
        err.contains("0 complete agent futures of 1000 steps: PCA needs at least 3000"),
        "{err}"
    );
    // 76 futures of 40 steps: past 50, short of the 120 numbers a future holds. The table's
    // header was printed, then "PCA needs at least 120 samples, got 76".
    let out = drivescript(&["dataset", "scripts/scenes", "--stride", "100000"]);
    let (stdout, err) = (
        String::from_utf8_lossy(&out.stdout),
        String::from_utf8_lossy(&out.stderr),
    );
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(
        err.contains("PCA needs at least 120 (at least 50, and one per number of a future")
            && err.contains("a smaller --stride")
            && !stdout.contains("| PCA components"),
        "{stdout}{err}"
    );
    // Futures of one step hold 3 numbers: rows for 4 to 32 components all read "1.00000
    // variance kept".
    let out = ok(&[
        "dataset",
        "scripts/scenes",
        "--history=1",
        "--future=1",
        "--stride=1",
    ]);
    assert!(!out.contains("| 4 |"), "{out}");
    assert!(
        out.contains("A future of 1 steps holds 3 numbers (x, y, heading per step): 3 components keep it exactly"),
        "{out}"
    );
    assert!(ok(&["dataset", "scripts/scenes"]).contains("| 32 |"));
    // A folder with no scene file said the same, as if its scenes were too short.
    let dir = tempfile::tempdir().unwrap();
    // A scenario given twice is counted twice, and said to be (it was counted in silence).
    let o = drivescript(&[
        "dataset",
        "scripts/scenes",
        "scripts/scenes/highway_cut_in.yaml",
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("warning: scenario ")
            && err.contains("was read 2 times (from scripts/scenes/highway_cut_in.yaml)"),
        "{err}"
    );
    assert_eq!(err.matches("warning:").count(), 1, "{err}");
    let err = fails(&["dataset", s(dir.path())]);
    assert!(
        err.contains(&format!(
            "{}: no scene file in it (supported: ",
            s(dir.path())
        )),
        "{err}"
    );
}

#[test]
fn test_scripts_refuses_to_pass_when_nothing_was_tested() {
    let dir = tempfile::tempdir().unwrap();
    // A directory without test files.
    let err = fails(&["test-scripts", s(dir.path())]);
    assert!(err.contains("no *.test.yaml files in"), "{err}");
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    std::fs::copy(
        root.join("scripts/cut_in.rhai"),
        dir.path().join("cut_in.rhai"),
    )
    .unwrap();
    let scenes = root.join("scripts/scenes/highway.yaml");
    // A file without cases, and a case that expects nothing.
    for (name, cases, want) in [
        ("empty.test.yaml", "cases: []\n".to_string(), "no cases"),
        (
            "nothing.test.yaml",
            format!(
                "cases:\n  - name: anything goes\n    scene: {}\n    params: {{cutter: 2, victim: 1}}\n    expect: {{}}\n",
                scenes.display()
            ),
            "`expect` checks nothing",
        ),
    ] {
        let f = dir.path().join(name);
        std::fs::write(&f, format!("script: cut_in.rhai\n{cases}")).unwrap();
        let out = drivescript(&["test-scripts", s(&f)]);
        let text = String::from_utf8_lossy(&out.stdout);
        assert_eq!(out.status.code(), Some(1), "{name}: {text}");
        assert!(text.contains(want) && text.contains("0 passed, 1 failed"), "{name}: {text}");
    }
}

#[test]
fn unknown_and_reserved_params_are_refused_with_the_scripts_parameters() {
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let err = fails(&[
        "cost",
        s(&scene),
        "--script",
        "scripts/no_collisions.rhai",
        "--param",
        "margn=30",
    ]);
    assert!(
        err.contains("\"margn\"") && err.contains("their parameters are margin, weight"),
        "{err}"
    );
    let err = fails(&[
        "cost",
        s(&scene),
        "--script",
        "scripts/no_collisions.rhai",
        "--param",
        "DT=5",
    ]);
    assert!(err.contains("built-in constant"), "{err}");
    // Known names still run.
    ok(&[
        "cost",
        s(&scene),
        "--script",
        "scripts/no_collisions.rhai",
        "--param",
        "margin=30",
    ]);
}

#[test]
fn parameter_errors_name_the_parameter_its_value_and_what_is_expected() {
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let cost = |params: &[&str]| {
        let mut a = vec![
            "cost",
            s(&scene),
            "--script",
            "scripts/cut_in.rhai",
            "--param",
        ];
        a.extend_from_slice(params);
        fails(&a)
    };
    // Each used to name no parameter: "no function agent (f64)", "no function - (&str |
    // ImmutableString | String, Dual)", and a 100 KB value quoted back whole.
    let err = cost(&["cutter=1.5", "victim=1"]);
    assert!(
        err.contains(
            "an agent id is a whole number, not a decimal number, from --param cutter=1.5"
        ),
        "{err}"
    );
    let err = cost(&["cutter=2", "victim=1", "gap="]);
    assert!(
        err.contains("parameter \"gap\": no value after `=`"),
        "{err}"
    );
    let err = cost(&["cutter=2", "victim=1", "gap=wide"]);
    assert!(
        err.contains(
            "parameter \"gap\" = \"wide\": the script takes a number here (its default is 5.0)"
        ),
        "{err}"
    );
    let huge = format!("gap={}", "9".repeat(100_000));
    let err = cost(&["cutter=2", "victim=1", &huge]);
    assert!(
        err.contains("parameter \"gap\": a value of 100000 characters") && err.len() < 400,
        "{err}"
    );
    // The checkers' ids too: `cutter=2.5` was judged as agent 2.
    let err = fails(&[
        "eval",
        s(&scene),
        "--task",
        "behaviour",
        "--behaviour",
        "cut_in",
        "--param",
        "cutter=2.5",
        "victim=1",
        "--baseline",
        "log",
    ]);
    assert!(
        err.contains("parameter \"cutter\" = \"2.5\" must be an agent id (a whole number)"),
        "{err}"
    );
}

#[test]
fn nothing_read_simulated_or_scored_is_an_error() {
    let dir = tempfile::tempdir().unwrap();
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    let err = fails(&["inspect", s(&empty)]);
    assert!(err.contains("no scene found"), "{err}");
    let err = fails(&["eval", s(&empty), "--task", "conditional"]);
    assert!(err.contains("nothing was scored"), "{err}");
    let err = fails(&[
        "simulate",
        s(&empty),
        "--checkpoint",
        "data/checkpoint",
        "-o",
        s(&dir.path().join("out")),
    ]);
    assert!(err.contains("no scene was simulated"), "{err}");
    // A behaviour's agents that cannot be checked are named, not scored as a row of dashes.
    let scene = samples().join("yaml/highway_cut_in.yaml");
    for (params, want) in [
        (
            ["cutter=2", "victim=77"],
            "error: highway-cut-in: cut_in: no agent 77 (victim)",
        ),
        (
            ["cutter=2", "victim=2"],
            "error: highway-cut-in: cut_in: cutter and victim are both agent 2",
        ),
    ] {
        let mut args = vec![
            "eval",
            s(&scene),
            "--task",
            "behaviour",
            "--behaviour",
            "cut_in",
        ];
        args.push("--param");
        args.extend(params);
        let err = fails(&args);
        assert!(err.contains(want), "{err}");
        assert!(err.contains("1 failed (the errors above)"), "{err}");
    }
}

#[test]
fn a_script_that_does_not_compile_is_said_once_before_any_scene() {
    let dir = tempfile::tempdir().unwrap();
    let bad = dir.path().join("bad.rhai");
    std::fs::write(&bad, "let a = agent(2)\nterm(\"x\" a.x.last());\n").unwrap();
    let out = dir.path().join("out");
    let err = fails(&[
        "simulate",
        s(&samples()),
        "--checkpoint",
        "data/checkpoint",
        "--script",
        s(&bad),
        "-o",
        s(&out),
    ]);
    // It was one error per scene (seven), and a run directory with run.json was left.
    assert_eq!(err.matches("syntax error").count(), 1, "{err}");
    assert!(
        err.contains("bad.rhai:2:1: syntax error: Expecting ';' to terminate this statement"),
        "{err}"
    );
    assert!(!err.contains("Syntax error"), "{err}");
    assert!(!out.exists());
    // A script that fails on every scene (an agent none has): nothing written, not even
    // the run record, which would refuse the next run's settings.
    std::fs::write(&bad, "let a = agent(999);\nterm(\"x\", a.x.last());\n").unwrap();
    let yaml = samples().join("yaml");
    let args = [
        "simulate",
        s(&yaml),
        "--checkpoint",
        "data/checkpoint",
        "--script",
        s(&bad),
        "-o",
        s(&out),
    ];
    let err = fails(&args);
    assert!(err.contains("2 scenes failed"), "{err}");
    assert!(!out.exists());
}

#[test]
fn an_error_names_its_cause_once() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("nope.json");
    let err = fails(&[
        "render",
        s(&samples().join("yaml/highway_cut_in.yaml")),
        "--rollout",
        s(&missing),
        "-o",
        s(&dir.path().join("x.gif")),
    ]);
    assert_eq!(err.matches("No such file or directory").count(), 1, "{err}");
    assert!(err.contains("nope.json"), "{err}");
}

#[test]
fn convert_refuses_to_write_over_its_input() {
    let dir = tempfile::tempdir().unwrap();
    let y = dir.path().join("s.yaml");
    std::fs::copy(samples().join("yaml/highway_cut_in.yaml"), &y).unwrap();
    let before = std::fs::read(&y).unwrap();
    let err = fails(&["convert", s(&y), "-o", s(&y)]);
    assert!(err.contains("-o: is the input itself"), "{err}");
    assert_eq!(std::fs::read(&y).unwrap(), before);
    // The same file by another name is the same file.
    let err = fails(&[
        "convert",
        s(&y),
        "-o",
        &format!("{}/./s.yaml", s(dir.path())),
    ]);
    assert!(err.contains("-o: is the input itself"), "{err}");
}

#[test]
fn eval_json_refuses_its_inputs_and_files_it_did_not_write() {
    let dir = tempfile::tempdir().unwrap();
    let y = dir.path().join("s.yaml");
    std::fs::copy(samples().join("yaml/highway_cut_in.yaml"), &y).unwrap();
    let before = std::fs::read(&y).unwrap();
    let eval = |json: &std::path::Path, scenes: &std::path::Path| {
        fails(&[
            "eval",
            s(scenes),
            "--task",
            "conditional",
            "--json",
            s(json),
        ])
    };
    // Its own input scene, by name or inside the directory given.
    let err = eval(&y, &y);
    assert!(err.contains("--json: is the input itself"), "{err}");
    let err = eval(&y, dir.path());
    assert!(
        err.contains("--json: is a scene file inside the input directory"),
        "{err}"
    );
    assert_eq!(std::fs::read(&y).unwrap(), before);
    // A checkpoint's config.json (or any file that is not an earlier `eval --json`).
    let ckpt = dir.path().join("ckpt");
    std::fs::create_dir(&ckpt).unwrap();
    let config = ckpt.join("config.json");
    std::fs::copy("data/checkpoint/config.json", &config).unwrap();
    let before = std::fs::read(&config).unwrap();
    let err = eval(&config, &y);
    assert!(
        err.contains("config.json: --json: already exists and is not an `eval --json` file"),
        "{err}"
    );
    assert_eq!(std::fs::read(&config).unwrap(), before);
    // An earlier evaluation's file is replaced.
    let e = dir.path().join("e.json");
    ok(&["eval", s(&y), "--task", "conditional", "--json", s(&e)]);
    ok(&["eval", s(&y), "--task", "conditional", "--json", s(&e)]);
    // One whole evaluation merged with itself (or a copy) would count its scenes twice.
    let copy = dir.path().join("copy.json");
    std::fs::copy(&e, &copy).unwrap();
    for pair in [[&e, &e], [&e, &copy]] {
        let err = fails(&["eval", "--merge", s(pair[0]), s(pair[1])]);
        assert!(err.contains("would count its scenes twice"), "{err}");
    }
    ok(&["eval", "--merge", s(&e)]);
}

#[test]
fn convert_and_render_replace_only_an_earlier_output_of_their_own_format() {
    let dir = tempfile::tempdir().unwrap();
    let y = samples().join("yaml/highway_cut_in.yaml");
    let p = |name: &str| dir.path().join(name);
    // Earlier outputs of the same format are replaced.
    for out in ["a.yaml", "a.json", "a.tfrecord"] {
        ok(&["convert", s(&y), "-o", s(&p(out))]);
        ok(&["convert", s(&y), "-o", s(&p(out))]);
    }
    for out in ["a.svg", "a.png", "a.gif"] {
        ok(&["render", s(&y), "--width", "64", "-o", s(&p(out))]);
        ok(&["render", s(&y), "--width", "64", "-o", s(&p(out))]);
    }
    // A user's file under the name, a picture of another format, a TFRecord of two scenarios:
    // refused, named, kept.
    let scene = drivescript::io::load_scene(&y, 0, &Default::default()).unwrap();
    drivescript::io::womd::write_file(&p("two.tfrecord"), &[scene.clone(), scene]).unwrap();
    std::fs::write(p("notes.yaml"), "my notes: [unclosed\n").unwrap();
    std::fs::write(p("notes.png"), "not a picture").unwrap();
    std::fs::copy(p("a.png"), p("png.svg")).unwrap();
    std::fs::copy(p("a.yaml"), p("scene.gif")).unwrap();
    for (command, out, what) in [
        ("convert", "notes.yaml", "a drivescript YAML scene"),
        ("convert", "two.tfrecord", "a WOMD TFRecord of one scenario"),
        ("convert", "a.svg", ""),
        ("render", "notes.png", "a PNG picture"),
        ("render", "png.svg", "an SVG picture"),
        ("render", "scene.gif", "a GIF picture"),
    ] {
        let before = std::fs::read(p(out)).unwrap();
        let err = fails(&[command, s(&y), "-o", s(&p(out))]);
        if what.is_empty() {
            assert!(err.contains("unknown output format"), "{err}");
        } else {
            assert!(
                err.contains(&format!(
                    "{}: -o: already exists and is not {what}: writing would replace it; \
                     remove it first or write to another file",
                    p(out).display()
                )),
                "{command} -o {out}: {err}"
            );
        }
        assert_eq!(std::fs::read(p(out)).unwrap(), before, "{out}");
    }
    // Never an input of the same command (a rollout named like a picture).
    let rollout = p("rollout.svg");
    std::fs::copy(p("a.json"), &rollout).unwrap();
    let before = std::fs::read(&rollout).unwrap();
    let err = fails(&["render", s(&y), "--rollout", s(&rollout), "-o", s(&rollout)]);
    assert!(err.contains("-o: is the input itself"), "{err}");
    assert_eq!(std::fs::read(&rollout).unwrap(), before);
    // A link at the output name, even to an earlier output of the format, is left alone: the
    // rename replaced the link itself with a file (issue 32).
    #[cfg(unix)]
    for (command, out) in [("convert", "a.yaml"), ("render", "a.png")] {
        let link = p(&format!("link-{out}"));
        std::os::unix::fs::symlink(p(out), &link).unwrap();
        let before = std::fs::read(p(out)).unwrap();
        let err = fails(&[command, s(&y), "-o", s(&link)]);
        assert!(
            err.contains(&format!(
                "{}: -o: is a symbolic link (to {}): writing would replace the link",
                link.display(),
                p(out).display()
            )),
            "{command}: {err}"
        );
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::read(p(out)).unwrap(), before);
    }
}

#[test]
fn convert_refuses_an_id_that_cannot_name_output_files() {
    let dir = tempfile::tempdir().unwrap();
    let y = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join("x.yaml");
    for (id, why) in [
        ("../../x", "starts with a dot"),
        ("a/b", "'/'"),
        ("a\u{202E}b", "U+202E"),
    ] {
        let err = fails(&["convert", s(&y), "--id", id, "-o", s(&out)]);
        assert!(
            err.contains("cannot name an output file") && err.contains(why),
            "{err}"
        );
        assert!(!out.exists());
    }
}

#[test]
fn a_scenario_id_too_long_to_name_an_output_file_is_refused_where_it_is_read() {
    // It used to be read (and printed whole by `inspect`) and refused only once a run had
    // sampled it and went to write `ID_0.json`.
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let highway = std::fs::read_to_string(root.join("scripts/scenes/highway.yaml")).unwrap();
    let long = "a".repeat(201);
    let yaml = dir.path().join("long.yaml");
    std::fs::write(
        &yaml,
        highway.replace("scenario_id: highway", &format!("scenario_id: {long}")),
    )
    .unwrap();
    let err = fails(&["inspect", s(&yaml)]);
    assert!(
        err.contains(s(&yaml))
            && err.contains("scenario_id: scenario id")
            && err.contains("is 201 bytes long, more than the 200"),
        "{err}"
    );
    assert!(!err.contains(&long), "the id is quoted whole: {err}");
    let short = dir.path().join("short.yaml");
    std::fs::write(
        &short,
        highway.replace(
            "scenario_id: highway",
            &format!("scenario_id: {}", &long[..200]),
        ),
    )
    .unwrap();
    ok(&["inspect", s(&short)]);
}

#[test]
fn names_read_from_files_with_control_or_invisible_characters_are_refused() {
    // A newline in an id faked an `error:` line in `inspect` (and in the LLM's prompt), an
    // escape sequence reached the terminal, a bidi control reordered what was shown.
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let xml = std::fs::read_to_string(samples().join("commonroad/USA_US101-3_3_T-1.xml"))
        .unwrap()
        .replacen(
            "benchmarkID=\"USA_US101-3_3_T-1\"",
            "benchmarkID=\"US101&#10;error: fake\"",
            1,
        );
    let cr = dir.path().join("hostile.xml");
    std::fs::write(&cr, xml.replace("US101&#10;error: fake", "US101&#x202E;x")).unwrap();
    let cr_nl = dir.path().join("hostile_nl.xml");
    std::fs::write(&cr_nl, xml).unwrap();
    let highway = std::fs::read_to_string(root.join("scripts/scenes/highway.yaml")).unwrap();
    let yaml = dir.path().join("hostile.yaml");
    std::fs::write(
        &yaml,
        highway.replace(
            "scenario_id: highway",
            "scenario_id: \"x\\e[2J\\e]0;pwned\\a\"",
        ),
    )
    .unwrap();
    for (file, want) in [
        (&cr, "contains the invisible character U+202E"),
        (&cr_nl, "contains the control character U+000A"),
        (&yaml, "scenario_id: scenario id \"x\\u{001B}[2J"),
    ] {
        let err = fails(&["inspect", s(file)]);
        assert!(
            err.contains(s(file)) && err.contains(want) && !err.contains('\u{1b}'),
            "{err}"
        );
        assert!(!err.contains("\nerror: fake"), "{err}");
        assert!(!err.contains('\u{202E}'), "{err}");
    }
    let out = run_test_file(
        dir.path(),
        "speed_limit.rhai",
        &format!(
            "  - name: \"ok\\nerror: fake \\e[2J\"\n    scene: {}\n    params: {{vehicle: 1, limit: 30}}\n    expect: {{total_below: 1.0}}\n",
            s(&root.join("scripts/scenes/highway.yaml"))
        ),
    );
    assert_eq!(out.status.code(), Some(1));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains("x.test.yaml: cases[0]: name \"ok\\u{000A}error: fake \\u{001B}[2J\" contains the control character U+000A"),
        "{text}"
    );
    assert!(
        !text.contains("\nerror: fake") && !text.contains('\u{1b}'),
        "{text}"
    );
    // Two cases of one name made two rows nobody could tell apart.
    let case = format!(
        "  - name: same\n    scene: {}\n    params: {{vehicle: 1, limit: 30}}\n    expect: {{total_below: 1.0}}\n",
        s(&root.join("scripts/scenes/highway.yaml"))
    );
    let out = run_test_file(dir.path(), "speed_limit.rhai", &format!("{case}{case}"));
    assert_eq!(out.status.code(), Some(1));
    let text = String::from_utf8_lossy(&out.stdout);
    assert!(
        text.contains(
            "x.test.yaml: cases[1]: the name \"same\" is also cases[0]'s: give each case its own name"
        ),
        "{text}"
    );
}

#[test]
fn convert_refuses_agent_ids_the_format_cannot_hold() {
    let dir = tempfile::tempdir().unwrap();
    let y = dir.path().join("big.yaml");
    std::fs::write(
        &y,
        "scenario_id: big\ndt: 0.1\nsteps: 3\ncurrent_step: 1\nroad: {lanes: 2, length: 100}\n\
         agents:\n  - id: 5000000000\n    type: vehicle\n    states: [[0,1.75,0], [1,1.75,0], [2,1.75,0]]\n",
    )
    .unwrap();
    let out = dir.path().join("big.tfrecord");
    let err = fails(&["convert", s(&y), "-o", s(&out)]);
    assert!(
        err.contains("scene big, agent 5000000000: WOMD track ids are 32-bit"),
        "{err}"
    );
    assert!(!out.exists());
    // YAML and rollout JSON hold 64-bit ids.
    ok(&["convert", s(&y), "-o", s(&dir.path().join("big2.yaml"))]);
}

#[test]
fn a_diverging_training_stops_with_an_error_and_writes_nothing() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("dv");
    let err = fails(&[
        "train",
        "--data",
        "scripts/scenes",
        "--out",
        s(&out),
        "--steps",
        "30",
        "--lr",
        "1e30",
        "--batch",
        "2",
        "--eval-every",
        "5",
    ]);
    assert!(err.contains("training diverged"), "{err}");
    assert!(!out.join("model.safetensors").exists());
    // Said "the last checkpoint written is kept" of a run that wrote none.
    assert!(
        err.contains("this run wrote no checkpoint") && !err.contains("is kept"),
        "{err}"
    );
}

/// `simulate` unguided (λ = 0) with the shipped checkpoint, plus `extra` flags.
fn unguided(
    scenes: &std::path::Path,
    out: &std::path::Path,
    extra: &[&str],
) -> std::process::Output {
    let mut a = vec![
        "simulate",
        s(scenes),
        "--checkpoint",
        "data/checkpoint",
        "--task",
        "unconditional",
        "--lambda",
        "0",
        "-o",
        s(out),
    ];
    a.extend_from_slice(extra);
    drivescript(&a)
}

/// `--resume --horizon 40` took the 20-step rollouts of a `--horizon 20` run as complete,
/// exit 0; the horizon is the run's, as its seed is.
#[test]
fn a_resumed_run_keeps_its_horizon() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let sim = |extra: &[&str]| unguided(&scene, &out, extra);
    let o = sim(&["--horizon", "20", "--steps", "8"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    for other in [&["--horizon", "40"][..], &[]] {
        let mut extra = vec!["--resume", "--steps", "8"];
        extra.extend_from_slice(other);
        let o = sim(&extra);
        let e = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{other:?}: {e}");
        assert!(e.contains("differs in settings.horizon: 20 there"), "{e}");
    }
    let o = sim(&["--resume", "--steps", "8", "--horizon", "20"]);
    assert!(
        o.status.success() && String::from_utf8_lossy(&o.stdout).contains("already complete"),
        "{o:?}"
    );
}

/// The table rows of an `eval` output, without the timing column.
fn table_rows(out: &str) -> Vec<String> {
    out.lines()
        .filter(|l| l.starts_with("| ") && !l.starts_with("| method"))
        .map(|l| l.rsplitn(3, '|').nth(2).unwrap_or(l).to_string())
        .collect()
}

#[test]
fn three_shards_and_a_merge_equal_the_single_run() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
    let sim = |out: &std::path::Path, extra: &[&str]| unguided(&scenes, out, extra);
    let (all, sharded) = (dir.path().join("all"), dir.path().join("sharded"));
    assert!(sim(&all, &[]).status.success());
    for i in 0..3 {
        let shard = format!("{i}/3");
        let o = sim(&sharded, &["--shard", &shard, "--resume"]);
        assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    }
    // The same rollouts, whichever way the scenes were split.
    let names = |d: &std::path::Path| {
        let mut v: Vec<String> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.ends_with(".json") && !n.ends_with("_costs.json"))
            .collect();
        v.sort();
        v
    };
    assert_eq!(names(&all), names(&sharded));
    assert!(names(&all).len() > 3);
    for n in names(&all) {
        assert_eq!(
            std::fs::read(all.join(&n)).unwrap(),
            std::fs::read(sharded.join(&n)).unwrap(),
            "{n}"
        );
    }
    let r: Value =
        serde_json::from_str(&std::fs::read_to_string(all.join("highway_0.json")).unwrap())
            .unwrap();
    assert_eq!(
        r["run"]["settings"]["seed"], 1,
        "every rollout says what made it"
    );
    // eval per shard, then merged: the single run's table.
    let eval = |extra: &[&str]| {
        let mut a = vec![
            "eval",
            s(&scenes),
            "--task",
            "conditional",
            "--baseline",
            "cv",
            "--rollouts",
            s(&all),
        ];
        a.extend_from_slice(extra);
        ok(&a)
    };
    let single = eval(&[]);
    let mut files = Vec::new();
    for i in 0..3 {
        let f = dir.path().join(format!("s{i}.json"));
        eval(&["--shard", &format!("{i}/3"), "--json", s(&f)]);
        files.push(f);
    }
    let fs: Vec<&str> = files.iter().map(|f| s(f)).collect();
    let mut args = vec!["eval", "--merge"];
    args.extend(&fs);
    let merged = ok(&args);
    assert!(merged.contains("merged 3 of 3 shards"), "{merged}");
    assert_eq!(table_rows(&single), table_rows(&merged));
    // A missing or repeated shard is refused.
    let err = fails(&["eval", "--merge", fs[0], fs[1]]);
    assert!(err.contains("shards 2/3 are missing"), "{err}");
    let err = fails(&["eval", "--merge", fs[0], fs[1], fs[2], fs[1]]);
    assert!(err.contains("is in both"), "{err}");
    // Figures no evaluation writes are refused, naming the file and the field: a negative
    // ADE, a scene count that would wrap when summed.
    let (k, shard) = files
        .iter()
        .enumerate()
        .map(|(k, f)| {
            let v: Value = serde_json::from_str(&std::fs::read_to_string(f).unwrap()).unwrap();
            (k, v)
        })
        .find(|(_, v)| v["merge"]["accumulators"][0]["ade"][0].is_number())
        .expect("a shard with scenes");
    let flags = shard["merge"]["accumulators"][0]["implausible"]
        .as_array()
        .unwrap()
        .len();
    assert!(flags > 0, "{shard}");
    let edited = dir.path().join("edited.json");
    for (field, value, says) in [
        (
            "ade",
            serde_json::json!([-1.0]),
            "ade[0] is -1: must be a distance",
        ),
        (
            "scenes",
            serde_json::json!(u64::MAX),
            "scenes is 18446744073709551615, but per_scene holds",
        ),
        // Per-agent lists longer than the scenes' agents and samples outweighed every other
        // shard's in the merged rates.
        (
            "implausible",
            serde_json::json!(vec![true; 100_000]),
            "implausible holds 100000 flags, and the scene rows' agent_samples sum to",
        ),
        (
            "collided",
            serde_json::json!(vec![true; flags + 1]),
            "collided holds",
        ),
    ] {
        let mut v = shard.clone();
        v["merge"]["accumulators"][0][field] = value;
        std::fs::write(&edited, v.to_string()).unwrap();
        let mut args = vec!["eval", "--merge", s(&edited)];
        args.extend(
            fs.iter()
                .enumerate()
                .filter(|(i, _)| *i != k)
                .map(|(_, f)| *f),
        );
        let err = fails(&args);
        assert!(
            err.contains(&format!("{}: merge.accumulators[0]", edited.display()))
                && err.contains(says),
            "{err}"
        );
    }
}

#[test]
fn a_run_directory_takes_one_run() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("run");
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let sim = |extra: &[&str]| unguided(&scene, &out, extra);
    assert!(sim(&[]).status.success());
    let run: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(run["command"], "simulate");
    assert_eq!(run["weights_crc32c"].as_str().unwrap().len(), 8);
    // The same command again: only with --resume, which finds the scene complete.
    let o = sim(&[]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert!(
        e.contains("already holds this run's outputs") && e.contains("--resume"),
        "{e}"
    );
    let o = sim(&["--resume"]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{t}");
    assert!(t.contains("1 scene already complete"), "{t}");
    // A rollout damaged since is no finished scene: simulated again, not reported complete
    // (and left for `eval` to fail on).
    let rollout = out.join("highway-cut-in_0.json");
    let good = std::fs::read(&rollout).unwrap();
    std::fs::write(&rollout, &good[..good.len() / 2]).unwrap();
    let o = sim(&["--resume"]);
    let t = String::from_utf8_lossy(&o.stdout);
    assert!(o.status.success(), "{t}");
    assert!(
        !t.contains("already complete") && t.contains("wrote 1 scene"),
        "{t}"
    );
    assert_eq!(
        std::fs::read(&rollout).unwrap(),
        good,
        "the same seed, the same rollout"
    );
    // The scene's file edited since: its outputs are not this scene's (they were taken for
    // them, "already complete", and eval scored them against the new recording).
    let copy = dir.path().join("edited.yaml");
    std::fs::copy(&scene, &copy).unwrap();
    let resumed = |scene: &std::path::Path| unguided(scene, &out, &["--resume"]);
    let o = resumed(&copy);
    assert!(
        o.status.success()
            && String::from_utf8_lossy(&o.stdout).contains("1 scene already complete")
    );
    let text = std::fs::read_to_string(&copy).unwrap();
    std::fs::write(&copy, text.replacen("length: 12.0", "length: 11.0", 1)).unwrap();
    let o = resumed(&copy);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert!(
        e.contains("highway-cut-in: the scene is not the one its outputs in")
            && e.contains("its file changed since")
            && e.contains("remove highway-cut-in_costs.json there to sample it again"),
        "{e}"
    );
    assert_eq!(std::fs::read(&rollout).unwrap(), good, "kept");
    // Another seed into the same directory: never.
    let o = sim(&["--resume", "--seed", "2"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert!(e.contains("settings.seed: 1 there, 2 here"), "{e}");
}

/// `simulate` without `--lambda` guides with the strength chosen for the checkpoint (its
/// config.json's `guidance_lambda`), else 3: the route-frame model, whose coefficient scales
/// follow urban traffic, under-steered NGSIM cut-ins at the shipped model's 3.
#[test]
fn simulate_guides_with_the_strength_chosen_for_its_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let ck = common::checkpoint_copy(dir.path());
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let lambda = |name: &str, extra: &[&str]| -> Value {
        let out = dir.path().join(name);
        let mut a = vec!["simulate", s(&scene), "--checkpoint", s(&ck), "--task"];
        a.extend([
            "unconditional",
            "--script",
            "scripts/cut_in.rhai",
            "--param",
        ]);
        a.extend(["cutter=2", "victim=1", "--samples", "1", "--steps", "8"]);
        a.extend(["--polish", "0", "--horizon", "10", "-o", s(&out)]);
        a.extend(extra);
        ok(&a);
        let r: Value = serde_json::from_str(
            &std::fs::read_to_string(out.join("highway-cut-in_0.json")).unwrap(),
        )
        .unwrap();
        r["run"]["settings"]["lambda"].clone()
    };
    assert_eq!(lambda("shipped", &[]), 3.0);
    let mut cfg: Value =
        serde_json::from_str(&std::fs::read_to_string(ck.join("config.json")).unwrap()).unwrap();
    cfg["guidance_lambda"] = serde_json::json!(6.5);
    std::fs::write(ck.join("config.json"), cfg.to_string()).unwrap();
    assert_eq!(lambda("chosen", &[]), 6.5);
    assert_eq!(lambda("given", &["--lambda", "2"]), 2.0, "the flag wins");
}

#[test]
fn a_run_resumed_after_its_checkpoint_config_changed_is_refused() {
    // Only the weights were checksummed: a config.json edited in place (another noise
    // schedule here) resumed the run with another sampler, exit 0.
    let dir = tempfile::tempdir().unwrap();
    let ck = common::checkpoint_copy(dir.path());
    let out = dir.path().join("run");
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let sim = |extra: &[&str]| {
        let mut a = vec!["simulate", s(&scene), "--checkpoint", s(&ck)];
        a.extend(["--task", "unconditional", "--lambda", "0", "-o", s(&out)]);
        a.extend(extra);
        drivescript(&a)
    };
    assert!(sim(&[]).status.success());
    let run: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("run.json")).unwrap()).unwrap();
    assert_eq!(run["config_crc32c"].as_str().unwrap().len(), 8);
    assert!(sim(&["--resume"]).status.success(), "unchanged, it resumes");
    let mut cfg: Value =
        serde_json::from_str(&std::fs::read_to_string(ck.join("config.json")).unwrap()).unwrap();
    cfg["config"]["edm"]["sigma_max"] = serde_json::json!(60.0);
    std::fs::write(ck.join("config.json"), cfg.to_string()).unwrap();
    let o = sim(&["--resume"]);
    let e = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{e}");
    assert!(e.contains("differs in config_crc32c"), "{e}");
    // A record written before the field resumes as it did.
    let mut old = run.clone();
    old.as_object_mut().unwrap().remove("config_crc32c");
    std::fs::write(out.join("run.json"), old.to_string()).unwrap();
    let o = sim(&["--resume"]);
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn eval_judges_the_rest_of_the_scene_against_the_unguided_twin() {
    // The twin drives the highway as recorded; the guided sample keeps vehicle 1 under its
    // speed limit, but stacks vehicle 3 on vehicle 1 and vehicle 4 on vehicle 2 from the
    // current step on: three vehicles the behaviour does not name collide, against none.
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let scene = root.join("scripts/scenes/highway.yaml");
    let (guided, twin) = (dir.path().join("guided"), dir.path().join("twin"));
    for d in [&guided, &twin] {
        std::fs::create_dir(d).unwrap();
    }
    ok(&["convert", s(&scene), "-o", s(&twin.join("highway.json"))]);
    let mut r: Value =
        serde_json::from_str(&std::fs::read_to_string(twin.join("highway.json")).unwrap()).unwrap();
    let c = r["current_step"].as_u64().unwrap() as usize;
    for (onto, from) in [(0, 2), (1, 3)] {
        let target = r["agents"][onto]["states"].as_array().unwrap().clone();
        let st = r["agents"][from]["states"].as_array_mut().unwrap();
        for (k, x) in st.iter_mut().enumerate().skip(c + 1) {
            *x = target[k].clone();
        }
    }
    std::fs::write(guided.join("highway.json"), r.to_string()).unwrap();
    fn eval<'a>(scene: &'a str, guided: &'a str, extra: &[&'a str]) -> Vec<&'a str> {
        let mut a = vec![
            "eval",
            scene,
            "--task",
            "behaviour",
            "--behaviour",
            "speed_limit",
            "--param",
            "vehicle=1",
            "limit=30",
            "--rollouts",
            guided,
        ];
        a.extend_from_slice(extra);
        a
    }
    let (sc, gd) = (s(&scene), s(&guided));
    // Without the twin, only what the behaviour names is judged: it passes.
    let out = ok(&eval(sc, gd, &[]));
    let row = out
        .lines()
        .find(|l| l.starts_with("| rollouts in"))
        .unwrap();
    assert!(
        row.contains("| speed_limit | 1 | 1.00 | 1.00 | 1.000 | 0.500 |"),
        "{out}"
    );
    // With it, the wreck behind is the guidance's doing.
    let json = dir.path().join("e.json");
    let out = ok(&eval(sc, gd, &["--unguided", s(&twin), "--json", s(&json)]));
    let row = out
        .lines()
        .find(|l| l.starts_with("| rollouts in"))
        .unwrap();
    assert!(
        row.contains("| speed_limit | 1 | 0.00 | 1.00 | 1.000 | 0.500 |"),
        "{out}"
    );
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let verdict = &v["methods"][0]["scenes"][0]["verdicts"][0];
    assert_eq!(verdict["collateral"]["collided"], 3, "{verdict}");
    assert_eq!(verdict["collateral"]["collided_unguided"], 0, "{verdict}");
    assert!(
        verdict["reason"]
            .as_str()
            .unwrap()
            .contains("3 other vehicles collide (unguided: 0)"),
        "{verdict}"
    );
    // The twin is the same scene's, or nothing is judged.
    let elsewhere = dir.path().join("elsewhere");
    std::fs::create_dir(&elsewhere).unwrap();
    let out = common::drivescript(&eval(sc, gd, &["--unguided", s(&elsewhere)]));
    assert_eq!(out.status.code(), Some(1));
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(err.contains("missing rollout for scene highway"), "{err}");
    let out = common::drivescript(&[
        "eval",
        s(&scene),
        "--task",
        "unconditional",
        "--rollouts",
        s(&guided),
        "--unguided",
        s(&twin),
    ]);
    assert_eq!(out.status.code(), Some(1));
    assert!(String::from_utf8_lossy(&out.stderr).contains("only --task behaviour"));
}

#[test]
fn eval_does_not_count_what_a_behaviour_asks_of_the_agents_it_names() {
    // Vehicle 1 stands, then backs up at up to 2 m/s: what `reverse` asks of it, so neither
    // its verdict nor the implausible column holds it against it; judged as a speed limit, the
    // same motion is a reversing car.
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let text = std::fs::read_to_string(root.join("scripts/scenes/highway.yaml"))
        .unwrap()
        .replace(
            "{id: 1, lane: 1, s: 60, speed: 20}",
            "{id: 1, lane: 1, s: 60, speed: 0}",
        );
    let scene = dir.path().join("highway.yaml");
    std::fs::write(&scene, text).unwrap();
    let rollouts = dir.path().join("r");
    std::fs::create_dir(&rollouts).unwrap();
    let file = rollouts.join("highway.json");
    ok(&["convert", s(&scene), "-o", s(&file)]);
    let mut r: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    let c = r["current_step"].as_u64().unwrap() as usize;
    let st = r["agents"][0]["states"].as_array_mut().unwrap();
    let (x0, y0, h) = (
        st[c][0].as_f64().unwrap(),
        st[c][1].as_f64().unwrap(),
        st[c][2].as_f64().unwrap(),
    );
    let mut back = 0.0;
    for (k, x) in st.iter_mut().enumerate().skip(c + 1) {
        let t = (k - c) as f64 * 0.1;
        back += 0.1 * 2.0 * t.min(1.0);
        x[0] = serde_json::json!(x0 - back * h.cos());
        x[1] = serde_json::json!(y0 - back * h.sin());
    }
    std::fs::write(&file, r.to_string()).unwrap();
    let row = |behaviour: &str, params: &[&str]| {
        let mut a = vec![
            "eval",
            s(&scene),
            "--task",
            "behaviour",
            "--behaviour",
            behaviour,
            "--rollouts",
            s(&rollouts),
            "--param",
        ];
        a.extend_from_slice(params);
        let out = ok(&a);
        out.lines()
            .find(|l| l.starts_with("| rollouts in"))
            .unwrap_or_else(|| panic!("{out}"))
            .to_string()
    };
    let asked = row("reverse", &["vehicle=1"]);
    assert!(
        asked.contains("| reverse | 1 | 1.00 | 1.00 | 0.000 | 0.000 |"),
        "{asked}"
    );
    let not_asked = row("speed_limit", &["vehicle=1", "limit=30"]);
    assert!(
        not_asked.contains("| speed_limit | 1 | 0.00 | 1.00 | 0.000 | 0.250 |"),
        "{not_asked}"
    );
}

#[test]
fn eval_judges_a_rollout_with_what_its_script_allowed_as_simulate_and_ask_did() {
    // Vehicle 4 of highway_stop is asked to back up at 2 m/s, and its script allows it:
    // judged as a speed limit, the sampler's verdict (sample::attempt, `ask`'s judge too)
    // passes it. `eval` over the rollout used to judge it without the allowance and fail it
    // for reversing: `ask` and `eval` disagreed on the same trajectories.
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let scene = root.join("scripts/scenes/highway_stop.yaml");
    let script = dir.path().join("back.rhai");
    std::fs::write(
        &script,
        "let a = agent(param(\"vehicle\"));\nallow(a, \"reverse\");\n\
         term(\"backs_up\", relu(a.long_speed + 2.0).mean());\n\
         term(\"under\", relu(a.long_speed - param(\"limit\") + 0.0 * param(\"from\")).mean());\n",
    )
    .unwrap();
    let out = dir.path().join("out");
    ok(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &[
            "--auto",
            "speed_limit",
            "--script",
            s(&script),
            "--param",
            "vehicle=4",
        ],
        s(&out),
    ));
    let read = |p: &std::path::Path| -> Value {
        serde_json::from_str(&std::fs::read_to_string(p).unwrap()).unwrap()
    };
    let costs = read(&out.join("highway-stop_costs.json"));
    let sample = &costs["samples"][0];
    // The known answer: vehicle 4 reverses, asked for, and the sampler's verdict passes.
    assert!(
        sample["realism"]
            .as_array()
            .unwrap()
            .iter()
            .any(|e| e["agent"] == 4 && e["kind"] == "reverse" && e["requested"] == true),
        "{sample}"
    );
    let judged = &sample["verdicts"][0];
    assert_eq!(judged["passed"], true, "{judged}");
    let allowed = serde_json::json!([{"agent": 4, "motion": "reverse"}]);
    assert_eq!(sample["allowed"], allowed);
    let rollout = read(&out.join("highway-stop_0.json"));
    assert_eq!(rollout["allowed"], allowed, "the rollout carries it");
    let params = ["--param", "vehicle=4", "limit=16", "from=1.6"];
    let eval = |rollouts: &std::path::Path, json: &std::path::Path| {
        let mut a = vec![
            "eval",
            s(&scene),
            "--task",
            "behaviour",
            "--behaviour",
            "speed_limit",
            "--rollouts",
            s(rollouts),
            "--unguided",
        ];
        let twins = rollouts.join("unguided");
        a.push(s(&twins));
        a.extend_from_slice(&params);
        a.extend(["--json", s(json)]);
        let table = ok(&a);
        let row = table
            .lines()
            .find(|l| l.starts_with("| rollouts in"))
            .unwrap_or_else(|| panic!("{table}"))
            .to_string();
        (
            row,
            read(json)["methods"][0]["scenes"][0]["verdicts"][0].clone(),
        )
    };
    // `eval` gives the sampler's verdict, and counts the allowed reversing as no fault.
    let (row, verdict) = eval(&out, &dir.path().join("allowed.json"));
    assert_eq!(verdict["passed"], judged["passed"], "{verdict}");
    assert_eq!(verdict["violations"], judged["violations"], "{verdict}");
    assert_eq!(verdict["reason"], judged["reason"], "{verdict}");
    assert!(row.contains("| speed_limit | 1 | 1.00 | 1.00 |"), "{row}");
    // The same trajectories without the allowance (a rollout written before rollouts carried
    // it, read as allowing nothing): the reversing fails the verdict and counts as
    // implausible.
    let bare = dir.path().join("bare");
    std::fs::create_dir_all(bare.join("unguided")).unwrap();
    let mut r = rollout.clone();
    r.as_object_mut().unwrap().remove("allowed");
    std::fs::write(bare.join("highway-stop_0.json"), r.to_string()).unwrap();
    std::fs::copy(
        out.join("unguided/highway-stop_0.json"),
        bare.join("unguided/highway-stop_0.json"),
    )
    .unwrap();
    let (bare_row, verdict) = eval(&bare, &dir.path().join("bare.json"));
    assert_eq!(verdict["passed"], false, "{verdict}");
    assert!(
        verdict["reason"]
            .as_str()
            .unwrap()
            .contains("but vehicle 4 reverses"),
        "{verdict}"
    );
    assert!(
        bare_row.contains("| speed_limit | 1 | 0.00 | 1.00 |"),
        "{bare_row}"
    );
    let implausible = |row: &str| -> f64 { row.split('|').nth(7).unwrap().trim().parse().unwrap() };
    assert!(
        implausible(&bare_row) > implausible(&row),
        "{row}\n{bare_row}"
    );
    // An allowance a script cannot make, or for an agent the scene lacks, is an error
    // naming the file and the entry.
    let file = bare.join("highway-stop_0.json");
    for (entry, says) in [
        (
            serde_json::json!({"agent": 4, "motion": "sprint"}),
            "unknown variant `sprint`, expected `reverse`",
        ),
        (
            serde_json::json!({"agent": 99, "motion": "reverse"}),
            "allowed[0]: the scene has no agent 99",
        ),
    ] {
        r["allowed"] = serde_json::json!([entry]);
        std::fs::write(&file, r.to_string()).unwrap();
        let o = drivescript(&[
            "eval",
            s(&scene),
            "--task",
            "behaviour",
            "--behaviour",
            "speed_limit",
            "--rollouts",
            s(&bare),
            "--param",
            "vehicle=4",
            "limit=16",
        ]);
        let err = String::from_utf8_lossy(&o.stderr);
        assert!(
            err.contains(&file.display().to_string()) && err.contains(says),
            "{err}"
        );
    }
}

#[test]
fn scenes_an_auto_run_skipped_are_skipped_by_eval_over_the_same_list() {
    // `simulate --auto cut_in` finds a cutter on the cut-in highway but not at the junction;
    // `eval` over both scenes and the run's unguided twins used to stop at the junction's
    // missing rollout.
    let dir = tempfile::tempdir().unwrap();
    let scenes = dir.path().join("scenes");
    std::fs::create_dir(&scenes).unwrap();
    for f in ["highway_cut_in.yaml", "junction.yaml"] {
        std::fs::copy(
            std::path::Path::new("scripts/scenes").join(f),
            scenes.join(f),
        )
        .unwrap();
    }
    let out_dir = dir.path().join("out");
    let out = ok(&simulate_args(
        s(&scenes),
        "data/checkpoint",
        &[
            "--auto",
            "cut_in",
            "--steps",
            "8",
            "--task",
            "unconditional",
        ],
        s(&out_dir),
    ));
    assert!(out.contains("no agents suited to cut_in; skipped"), "{out}");
    for d in [out_dir.clone(), out_dir.join("unguided")] {
        assert!(d.join("junction_skipped.json").is_file(), "{}", d.display());
    }
    let out = ok(&[
        "eval",
        s(&scenes),
        "--task",
        "unconditional",
        "--rollouts",
        s(&out_dir.join("unguided")),
    ]);
    assert!(
        out.contains("1 scenes skipped: the run that wrote --rollouts left them out"),
        "{out}"
    );
    // --resume counts the skipped scene as done.
    let resume = simulate_args(
        s(&scenes),
        "data/checkpoint",
        &[
            "--auto",
            "cut_in",
            "--steps",
            "8",
            "--task",
            "unconditional",
            "--resume",
        ],
        s(&out_dir),
    );
    let out = ok(&resume);
    assert!(!out.contains("no agents suited"), "{out}");
    // The skipped scene's file edited since: it was taken as skipped for good, whatever it
    // now holds.
    let junction = scenes.join("junction.yaml");
    let text = std::fs::read_to_string(&junction).unwrap();
    std::fs::write(
        &junction,
        text.replace("s: 35, speed: 10", "s: 36, speed: 10"),
    )
    .unwrap();
    let e = fails(&resume);
    assert!(
        e.contains("junction: the scene is not the one its outputs in")
            && e.contains("remove junction_skipped.json and unguided/junction_skipped.json"),
        "{e}"
    );
}

#[test]
fn a_conditional_eval_with_no_recorded_future_is_an_error_not_a_row_of_dashes() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("now.yaml");
    std::fs::write(
        &scene,
        "steps: 11\ncurrent_step: 10\nroad: {lanes: 2, lane_width: 3.6, length: 300}\nagents:\n  - {id: 1, lane: 0, s: 50, speed: 20}\n",
    )
    .unwrap();
    let err = fails(&[
        "eval",
        s(&scene),
        "--task",
        "conditional",
        "--baseline",
        "cv",
    ]);
    assert!(
        err.contains("nothing was scored") && err.contains("recorded future"),
        "{err}"
    );
    // The unconditional table of the same scene was a row of dashes with exit 0: a scene was
    // counted, though no agent is observed at any future step.
    let err = fails(&[
        "eval",
        s(&scene),
        "--task",
        "unconditional",
        "--baseline",
        "cv",
    ]);
    assert!(err.contains("nothing was scored"), "{err}");
}

/// A script with two terms nothing can move and one guard the log leaves at 0.
const DEAD_TERMS: &str = "let a = agent(1);\n\
    term(\"moves\", a.x.last());\n\
    term(\"never\", relu(a.speed - 50.0).mean());\n\
    term(\"nil\", 0.0 * a.x.last());\n\
    term(\"guard\", no_collision_cost(vehicles(), 0.5));\n\
    term(\"flat\", 1.0 + 0.0 * a.x.last());\n";

#[test]
fn cost_and_simulate_name_terms_no_perturbed_future_moves() {
    let dir = tempfile::tempdir().unwrap();
    let script = dir.path().join("dead.rhai");
    std::fs::write(&script, DEAD_TERMS).unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let scene = root.join("scripts/scenes/highway.yaml");
    // `cost` warns (the user may keep a guard the probes miss) and still evaluates.
    let out = drivescript(&["cost", s(&scene), "--script", s(&script), "--json"]);
    assert!(out.status.success());
    let err = String::from_utf8_lossy(&out.stderr);
    let line = |term: &str, n: usize| {
        format!("dead.rhai:{n}: term \"{term}\": it is 0 with a zero gradient")
    };
    for (t, n) in [("never", 3), ("nil", 4)] {
        assert!(
            err.contains(&line(t, n)) && err.contains("can never steer"),
            "{err}"
        );
    }
    assert!(
        !err.contains("\"guard\"") && !err.contains("\"moves\""),
        "{err}"
    );
    // A constant other than 0 passed without a word.
    assert!(
        err.contains(
            "dead.rhai:6: term \"flat\": its gradient is zero on the recorded future and on"
        ) && err.contains("(its value, 1, does not follow the motion)"),
        "{err}"
    );
    let v: Value = serde_json::from_slice(&out.stdout).unwrap();
    assert_eq!(v["warnings"].as_array().unwrap().len(), 3, "{v}");
    // `simulate` says it once per run, however many scenes share the script, and keeps it in
    // the costs report.
    let out_dir = dir.path().join("sim");
    let o = drivescript(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &["--script", s(&script), "--steps", "8", "--polish", "0"],
        s(&out_dir),
    ));
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert_eq!(err.matches("term \"never\"").count(), 1, "{err}");
    assert!(
        err.contains(&format!("warning: highway: {}", s(&script)))
            && err.contains("said once per run"),
        "{err}"
    );
    let costs: Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("highway_costs.json")).unwrap())
            .unwrap();
    let w = costs["warnings"].as_array().unwrap();
    assert!(
        w.len() == 3 && w[0].as_str().unwrap().contains(&line("never", 3)),
        "{costs}"
    );
}

#[test]
fn a_verdict_measure_that_is_not_finite_is_written_as_such_not_as_null() {
    // Vehicle 1 turned round for the whole future ends on no lane (no lane runs that way):
    // its offset from a lane centre is infinite, which JSON has no number for.
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let scene = root.join("scripts/scenes/highway.yaml");
    let rollouts = dir.path().join("r");
    std::fs::create_dir(&rollouts).unwrap();
    let file = rollouts.join("highway.json");
    ok(&["convert", s(&scene), "-o", s(&file)]);
    let mut r: Value = serde_json::from_str(&std::fs::read_to_string(&file).unwrap()).unwrap();
    let c = r["current_step"].as_u64().unwrap() as usize;
    for st in r["agents"][0]["states"]
        .as_array_mut()
        .unwrap()
        .iter_mut()
        .skip(c + 1)
    {
        st[2] = (st[2].as_f64().unwrap() + std::f64::consts::PI).into();
    }
    std::fs::write(&file, r.to_string()).unwrap();
    let json = dir.path().join("e.json");
    ok(&[
        "eval",
        s(&scene),
        "--task",
        "behaviour",
        "--behaviour",
        "rightmost_lane",
        "--param",
        "vehicle=1",
        "--rollouts",
        s(&rollouts),
        "--json",
        s(&json),
    ]);
    let v: Value = serde_json::from_str(&std::fs::read_to_string(&json).unwrap()).unwrap();
    let verdict = &v["methods"][0]["scenes"][0]["verdicts"][0];
    assert_eq!(verdict["reason"], "ends on no lane", "{verdict}");
    assert_eq!(
        verdict["measured"]["end_offset_from_centre"], "inf",
        "{verdict}"
    );
    assert_eq!(verdict["measured"]["end_lane"], -1.0, "{verdict}");
}

#[test]
fn guidance_is_one_flag_with_one_default_on_every_command_that_samples() {
    for cmd in ["simulate", "ask", "demo"] {
        let help = ok(&[cmd, "--help"]);
        let flag = help
            .split("--guidance <GUIDANCE>")
            .nth(1)
            .unwrap_or_else(|| panic!("{cmd} has no --guidance:\n{help}"));
        // It has a default, so the first `[default: ` after its name is its own.
        let (entry, default) = flag.split_once("[default: ").unwrap();
        assert!(
            default.starts_with("output]") && entry.contains("denoiser"),
            "{cmd}: {entry}"
        );
        assert!(!help.contains("--through-denoiser"), "{cmd}:\n{help}");
    }
    // The old name still reads, as --guidance denoiser; given with --guidance it is refused.
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("commonroad/USA_US101-3_3_T-1.xml");
    let run = dir.path().join("m");
    let out = drivescript(&[
        "ask",
        s(&scene),
        "vehicle 401 cuts in front of vehicle 399",
        "--llm",
        "manual",
        "--through-denoiser",
        "-o",
        s(&run),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{err}");
    assert!(
        err.contains("--through-denoiser is the old name of --guidance denoiser"),
        "{err}"
    );
    let state: Value =
        serde_json::from_str(&std::fs::read_to_string(run.join("state.json")).unwrap()).unwrap();
    assert_eq!(state["config"]["guidance"], "denoiser");
    let fresh = dir.path().join("f");
    ok(&[
        "ask",
        s(&scene),
        "vehicle 401 cuts in front of vehicle 399",
        "--llm",
        "manual",
        "-o",
        s(&fresh),
    ]);
    let state: Value =
        serde_json::from_str(&std::fs::read_to_string(fresh.join("state.json")).unwrap()).unwrap();
    assert_eq!(state["config"]["guidance"], "output");
    let out = drivescript(&[
        "ask",
        s(&scene),
        "vehicle 401 cuts in front of vehicle 399",
        "--through-denoiser",
        "--guidance",
        "output",
        "-o",
        s(&dir.path().join("x")),
    ]);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(2), "{err}");
    assert!(err.contains("--guidance"), "{err}");
}

#[test]
fn a_byte_order_mark_is_dropped_from_every_text_file_read() {
    // Scripts and test files saved by Windows editors start with one; it was reported as an
    // unexpected character (scripts) or a missing field (test files).
    let dir = tempfile::tempdir().unwrap();
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let bom = |name: &str, text: &str| {
        let p = dir.path().join(name);
        std::fs::write(&p, format!("\u{FEFF}{text}")).unwrap();
        p
    };
    let script = bom(
        "cut_in.rhai",
        &std::fs::read_to_string(root.join("scripts/cut_in.rhai")).unwrap(),
    );
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = ok(&[
        "cost",
        s(&scene),
        "--script",
        s(&script),
        "--param",
        "cutter=2",
        "victim=1",
    ]);
    assert!(out.contains("total"), "{out}");
    let tests = std::fs::read_to_string(root.join("scripts/cut_in.test.yaml"))
        .unwrap()
        .replace(
            "script: cut_in.rhai",
            &format!("script: {}", root.join("scripts/cut_in.rhai").display()),
        )
        .replace(
            "scenes/",
            &format!("{}/", root.join("scripts/scenes").display()),
        );
    let t = bom("cut_in.test.yaml", &tests);
    let out = ok(&["test-scripts", s(&t)]);
    assert!(out.contains("passed, 0 failed"), "{out}");
}

#[test]
fn cost_checks_a_rollout_as_eval_and_render_do() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let rec = dir.path().join("rec.json");
    ok(&["convert", s(&scene), "-o", s(&rec)]);
    let script = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/cut_in.rhai");
    let cost = |r: &std::path::Path| {
        common::drivescript(&[
            "cost",
            s(&scene),
            "--script",
            s(&script),
            "--rollout",
            s(r),
            "--param",
            "cutter=2",
            "victim=1",
        ])
    };
    assert!(cost(&rec).status.success());
    let mut v: Value = serde_json::from_str(&std::fs::read_to_string(&rec).unwrap()).unwrap();
    v["agents"][0]["states"][20][0] = serde_json::json!(1e300);
    let bad = dir.path().join("bad.json");
    std::fs::write(&bad, serde_json::to_string(&v).unwrap()).unwrap();
    let out = cost(&bad);
    let err = String::from_utf8_lossy(&out.stderr);
    assert_eq!(out.status.code(), Some(1), "{err}");
    assert!(err.contains("bad.json"), "{err}");
    let render = fails(&[
        "render",
        s(&scene),
        "--rollout",
        s(&bad),
        "-o",
        s(&dir.path().join("x.svg")),
    ]);
    assert!(render.contains("bad.json"), "{render}");
    // A rollout that stops at the current step was told to hold the recording's 91 steps
    // ("agent 1 has 11 states in the rollout, the scene has 91 steps"), though 12 pass.
    let mut v: Value = serde_json::from_str(&std::fs::read_to_string(&rec).unwrap()).unwrap();
    for a in v["agents"].as_array_mut().unwrap() {
        a["states"].as_array_mut().unwrap().truncate(11);
    }
    let now = dir.path().join("now.json");
    std::fs::write(&now, serde_json::to_string(&v).unwrap()).unwrap();
    let out = cost(&now);
    let err = String::from_utf8_lossy(&out.stderr);
    assert!(
        err.contains("now.json")
            && err.contains("the rollout stops at the current step (step 10, 11 states)")
            && !err.contains("91"),
        "{err}"
    );
}

#[test]
fn eval_refuses_a_parameter_the_behaviour_checker_does_not_read() {
    // `gapp=30` was dropped without a word: the table was cut_in's with its default gap,
    // exit 0.
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let run = |behaviour: &str, params: &[&str]| {
        let args = [
            &[
                "eval",
                s(&scene),
                "--task",
                "behaviour",
                "--behaviour",
                behaviour,
                "--param",
            ][..],
            params,
        ]
        .concat();
        fails(&args)
    };
    let err = run("cut_in", &["cutter=2", "victim=1", "gapp=30"]);
    assert!(
        err.contains("--param")
            && err.contains("cut_in: parameter \"gapp\"")
            && err.contains("its parameters are cutter, victim"),
        "{err}"
    );
    let err = run("follow", &["follower=2", "leader=1", "gapp=30"]);
    assert!(
        err.contains("its parameters are follower, leader, gap"),
        "{err}"
    );
    let err = run("no_collisions", &["vehicle=1"]);
    assert!(err.contains("it takes no parameters"), "{err}");
    // The names the checker reads still pass, optional ones too.
    ok(&[
        "eval",
        s(&scene),
        "--task",
        "behaviour",
        "--behaviour",
        "follow",
        "--param",
        "follower=1",
        "leader=2",
        "gap=12",
    ]);
}

#[test]
fn eval_refuses_flags_its_task_would_ignore() {
    // Each was dropped without a word: a conditional table printed for a request with
    // behaviour parameters, four samples asked of baselines that have one.
    let scene = samples().join("yaml/highway_cut_in.yaml");
    for (flags, want) in [
        (
            &["--task", "conditional", "--param", "cutter=2"][..],
            "--param: only --task behaviour",
        ),
        (
            &["--task", "conditional", "--behaviour", "cut_in"],
            "--behaviour: only --task behaviour",
        ),
        (
            &["--task", "unconditional", "--auto"],
            "--auto: only --task behaviour",
        ),
        (
            &["--task", "unconditional", "--all-steps"],
            "--all-steps: only --task conditional",
        ),
        (
            &["--task", "conditional", "--samples", "4"],
            "--samples 4: the number of samples per scene in --rollouts",
        ),
    ] {
        let err = fails(&[&["eval", s(&scene)][..], flags].concat());
        assert!(err.contains(want), "{flags:?}: {err}");
    }
    // The first of two samples was scored as if it were the run.
    let dir = tempfile::tempdir().unwrap();
    let rollouts = dir.path().join("sim");
    let fast = ["--steps", "8", "--polish", "0", "--samples", "2"];
    ok(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &fast,
        s(&rollouts),
    ));
    let err = fails(&[
        "eval",
        s(&scene),
        "--task",
        "conditional",
        "--rollouts",
        s(&rollouts),
    ]);
    assert!(
        err.contains("sampled 2 per scene (its run.json): pass --samples 2"),
        "{err}"
    );
    for flag in [
        ["--horizon", "40"],
        ["--behaviour", "cut_in"],
        ["--param", "cutter=2"],
    ] {
        let out = drivescript(&[&["eval", "--merge", "shard.json"][..], &flag].concat());
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{flag:?}: {err}");
        assert!(err.contains("cannot be used with"), "{flag:?}: {err}");
    }
}

#[test]
fn inspect_refuses_agent_flags_without_agents() {
    // --keep was refused without --agents, --max-agents and --horizon silently dropped.
    let scene = samples().join("yaml/highway_cut_in.yaml");
    for flag in [["--max-agents", "3"], ["--horizon", "5"]] {
        let out = drivescript(&[&["inspect", s(&scene)][..], &flag].concat());
        let err = String::from_utf8_lossy(&out.stderr);
        assert_eq!(out.status.code(), Some(2), "{flag:?}: {err}");
        assert!(err.contains("--agents"), "{flag:?}: {err}");
    }
    ok(&["inspect", s(&scene), "--agents", "--max-agents", "3"]);
}

#[test]
fn bench_io_refuses_a_data_directory_without_scenes() {
    // Timed as a row of 0 scenes at "inf" ms a scene and NaN MB/s, then its re-encoding failed
    // naming an empty file in bench's own temporary directory (issue 32).
    let dir = tempfile::tempdir().unwrap();
    let womd = dir.path().join("w.tfrecord");
    let err = fails(&[
        "bench",
        "io",
        "--data",
        s(dir.path()),
        "--seconds",
        "0.05",
        "--womd-out",
        s(&womd),
    ]);
    assert!(
        err.contains(&format!(
            "--data {}: no scene file in it, so there is nothing to time",
            dir.path().display()
        )) && !err.contains("drivescript-bench-"),
        "{err}"
    );
    assert!(!womd.exists());
}

#[test]
fn bench_io_and_dataset_report_a_bad_file_and_go_on_with_the_rest() {
    // Both stopped at the first bad file (other commands report it and go on), and bench
    // called the set "CommonRoad/any".
    let dir = tempfile::tempdir().unwrap();
    for f in ["highway_cut_in.yaml", "curved_two_lanes.yaml"] {
        std::fs::copy(samples().join("yaml").join(f), dir.path().join(f)).unwrap();
    }
    std::fs::write(dir.path().join("a_bad.yaml"), "steps: [oops\n").unwrap();
    let o = drivescript(&["bench", "io", "--data", s(dir.path()), "--seconds", "0.05"]);
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert_eq!(o.status.code(), Some(1), "{out}{err}");
    assert!(
        err.contains("--data: ") && err.contains("a_bad.yaml"),
        "{err}"
    );
    assert!(
        out.contains(&format!("--data {} (2 of 3 files)", dir.path().display()))
            && out.contains("## Frenet projection"),
        "{out}"
    );
    let o = drivescript(&["dataset", s(dir.path()), "--history=1", "--future=1"]);
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert_eq!(o.status.code(), Some(1), "{out}{err}");
    assert!(err.contains("a_bad.yaml"), "{err}");
    assert!(
        out.contains("1 sources or records could not be read (above); the rest:")
            && out.contains("2 scenes, 2 long enough"),
        "{out}"
    );
    // None readable: said, not timed.
    std::fs::remove_file(dir.path().join("highway_cut_in.yaml")).unwrap();
    std::fs::remove_file(dir.path().join("curved_two_lanes.yaml")).unwrap();
    let err = fails(&["bench", "io", "--data", s(dir.path()), "--seconds", "0.05"]);
    assert!(
        err.contains("none of its 1 scene files could be read"),
        "{err}"
    );
}

#[test]
fn bench_cost_refuses_a_scene_of_fewer_than_two_vehicles_before_its_table() {
    // One agent panicked (index out of bounds); a pedestrian as the second agent printed two
    // rows of the table, then stopped at no_collisions.rhai.
    let dir = tempfile::tempdir().unwrap();
    let head = "dt: 0.1\nsteps: 91\ncurrent_step: 10\nroad: {lanes: 2, lane_width: 3.6, \
                length: 400, segments: 1, speed_limit: 29}\nego: 1\nagents:\n  - {id: 1, lane: 0, \
                s: 60, speed: 24}\n";
    for (name, more) in [
        ("one", ""),
        (
            "walker",
            "  - {id: 2, type: pedestrian, lane: 1, s: 70, speed: 1}\n",
        ),
    ] {
        let path = dir.path().join(format!("{name}.yaml"));
        std::fs::write(&path, format!("scenario_id: {name}\n{head}{more}")).unwrap();
        let out = drivescript(&["bench", "cost", "--scene", s(&path), "--seconds", "0.05"]);
        let (stdout, err) = (
            String::from_utf8_lossy(&out.stdout),
            String::from_utf8_lossy(&out.stderr),
        );
        assert_eq!(out.status.code(), Some(1), "{name}: {err}");
        assert!(
            err.contains("the bench scene has 1 vehicle(s)")
                && err.contains("needs at least two (--scene)")
                && !err.contains("panicked")
                && !stdout.contains("| cut_in"),
            "{name}: {stdout}{err}"
        );
    }
}

#[test]
fn bench_refuses_flags_of_another_benchmark_and_outputs_over_what_it_did_not_write() {
    // Each flag was dropped without a word by the benchmarks that do not read it.
    for (args, want) in [
        (
            &["bench", "cost", "--export", "x.safetensors"][..],
            "--export: `bench cost` does not read it (only `bench sample` does)",
        ),
        (&["bench", "io", "--repeat", "2"], "--repeat: `bench io`"),
        (
            &["bench", "sample", "--seconds", "2"],
            "--seconds: `bench sample`",
        ),
    ] {
        let err = fails(args);
        assert!(err.contains(want), "{args:?}: {err}");
    }
    // --womd-out replaced a user's file, and re-encoded an input over itself.
    let dir = tempfile::tempdir().unwrap();
    let mine = dir.path().join("mine.tfrecord");
    std::fs::write(&mine, "mine").unwrap();
    let err = fails(&["bench", "io", "--womd-out", s(&mine)]);
    assert!(
        err.contains("already exists and is not a WOMD TFRecord"),
        "{err}"
    );
    assert_eq!(std::fs::read_to_string(&mine).unwrap(), "mine");
    let data = dir.path().join("data");
    std::fs::create_dir(&data).unwrap();
    let input = data.join("us101.tfrecord");
    let scene = samples().join("commonroad/USA_US101-3_3_T-1.xml");
    ok(&["convert", s(&scene), "-o", s(&input)]);
    let before = std::fs::read(&input).unwrap();
    let err = fails(&["bench", "io", "--data", s(&data), "--womd-out", s(&input)]);
    assert!(err.contains("inside the input directory"), "{err}");
    assert_eq!(std::fs::read(&input).unwrap(), before);
    // --womd that is not a file: the table's header was printed before the error, which
    // said "loading the WOMD → scenes (x) scenes".
    #[cfg(unix)]
    {
        let fifo = dir.path().join("fifo");
        assert!(std::process::Command::new("mkfifo")
            .arg(&fifo)
            .status()
            .unwrap()
            .success());
        for (path, want) in [(&fifo, "a FIFO, socket or device"), (&data, "a directory")] {
            let o = drivescript(&["bench", "io", "--womd", s(path)]);
            let (out, err) = (
                String::from_utf8_lossy(&o.stdout),
                String::from_utf8_lossy(&o.stderr),
            );
            assert_eq!(o.status.code(), Some(1), "{err}");
            assert!(out.is_empty(), "{out}");
            assert!(
                err.contains(&format!("--womd {}: not a regular file ({want}", s(path))),
                "{err}"
            );
        }
    }
}

#[test]
fn bench_sample_times_a_checkpoint_with_the_inputs_it_was_trained_with() {
    // bench sample replaced the checkpoint's window with the paper's, inputs included: a
    // --nearest-lane-pose checkpoint failed with "shape mismatch in matmul", a --route-times
    // one with "the batch has no route inputs (window.route_times = 0)", a --route-frame one
    // with "the batch has no routes (window.route_frame = false)".
    let dir = tempfile::tempdir().unwrap();
    for (name, flag) in [
        ("nearest", &["--nearest-lane-pose"][..]),
        ("route", &["--route-times", "4"]),
        ("route_frame", &["--route-frame"]),
    ] {
        let ckpt = dir.path().join(name);
        let mut args = vec![
            "train",
            "--data",
            "scripts/scenes",
            "--out",
            s(&ckpt),
            "--steps",
            "2",
            "--eval-every",
            "1",
        ];
        args.extend(flag);
        ok(&args);
        let out = ok(&[
            "bench",
            "sample",
            "--repeat",
            "1",
            "--only",
            "unguided",
            "--checkpoint",
            s(&ckpt),
        ]);
        assert!(out.contains("| sampling, unguided |"), "{name}: {out}");
    }
}

#[test]
fn a_file_name_with_escape_sequences_reaches_no_terminal() {
    // A per-file error quoted the name as it is: the rest of the terminal turned red.
    let dir = tempfile::tempdir().unwrap();
    std::fs::write(dir.path().join("a\u{1b}[31mred.yaml"), "garbage: [").unwrap();
    for cmd in [
        &["inspect", s(dir.path())][..],
        &["eval", s(dir.path()), "--task", "conditional"],
    ] {
        let err = String::from_utf8_lossy(&drivescript(cmd).stderr).into_owned();
        assert!(err.contains("a\\u{001B}[31mred.yaml"), "{cmd:?}: {err}");
        assert!(!err.contains('\u{1b}'), "{cmd:?}: {err:?}");
    }
}

/// A long `--role` value is quoted cut, with its length, not echoed whole (clap's own "invalid
/// value" line quoted all 5000 characters, and the parser's message again).
#[test]
fn a_long_role_value_is_quoted_cut_with_its_length() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join("x.svg");
    for value in ["x".repeat(5000), format!("1={}", "x".repeat(5000))] {
        // A usage error: clap's exit status 2, as for every other bad flag value.
        let run = drivescript(&["render", s(&scene), "--role", &value, "-o", s(&out)]);
        assert_eq!(run.status.code(), Some(2));
        let err = String::from_utf8_lossy(&run.stderr).into_owned();
        assert!(err.len() < 600, "{} bytes: {err}", err.len());
        assert!(
            err.contains("invalid value for '--role")
                && err.contains(&format!("… ({} characters)", value.chars().count())),
            "{err}"
        );
    }
    let run = drivescript(&[
        "render",
        s(&scene),
        "--role",
        "1=cut\u{202E}ter",
        "-o",
        s(&out),
    ]);
    let err = String::from_utf8_lossy(&run.stderr).into_owned();
    assert!(err.contains("1 to 32 printable characters"), "{err}");
}

/// `--role 1=cutter,2=victim` (two roles in one value) labelled agent 1 "cutter,2=victim" and
/// left agent 2 plain, exit 0. A role holding '=' is refused, naming the repeated flag.
#[test]
fn two_roles_in_one_role_value_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join("x.svg");
    for value in ["1=cutter,2=victim", "1=cutter 2=victim", "1=a=b"] {
        let run = drivescript(&["render", s(&scene), "--role", value, "-o", s(&out)]);
        assert_eq!(run.status.code(), Some(2), "{value}");
        let err = String::from_utf8_lossy(&run.stderr).into_owned();
        assert!(
            err.contains(&format!(
                "'{value}': a role cannot hold '=': give --role once per agent"
            )),
            "{err}"
        );
        assert!(!out.exists());
    }
    ok(&[
        "render",
        s(&scene),
        "--role",
        "1=cutter",
        "--role",
        "2=victim",
        "-o",
        s(&out),
    ]);
}

/// Every flag whose value is checked quotes a long bad value cut to 64 characters with its
/// length, once or twice, never whole: clap's "invalid value '…'" line and tip, and the
/// library's own messages (behaviour names, the LLM server's URL and model, token field, town
/// names, requests the rules planner reads), each echoed all 5000 characters.
#[test]
fn every_checked_flag_quotes_a_long_bad_value_cut_with_its_length() {
    let dir = tempfile::tempdir().unwrap();
    let yaml = samples().join("yaml/highway_cut_in.yaml");
    let scene = s(&yaml);
    let ckpt = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/checkpoint");
    let ckpt = s(&ckpt);
    let out = dir.path().join("out");
    let out = s(&out);
    let long = "x".repeat(5000);
    let v = long.as_str();
    let sim = |flag: &'static str, more: &[&'static str]| -> Vec<String> {
        let mut a = vec!["simulate", scene, "--checkpoint", ckpt, "-o", out];
        a.extend(more);
        a.extend([flag, v]);
        a.into_iter().map(String::from).collect()
    };
    let ask = |flag: &'static str| -> Vec<String> {
        let mut a = vec!["ask", scene, "vehicle 1 drives off the road", "-o", out];
        for (f, value) in [
            ("--llm", "http"),
            ("--model", "m"),
            ("--llm-url", "http://127.0.0.1:9/v1"),
            (flag, v),
        ] {
            if f != flag || value == v {
                a.extend([f, value]);
            }
        }
        a.into_iter().map(String::from).collect()
    };
    let args = |a: &[&str]| -> Vec<String> { a.iter().map(|x| x.to_string()).collect() };
    // (arguments, what the message names)
    let cases: Vec<(Vec<String>, &str)> = vec![
        (sim("--task", &[]), "--task"),
        (sim("--samples", &[]), "--samples"),
        (sim("--steps", &[]), "--steps"),
        (sim("--shard", &[]), "--shard"),
        (sim("--guidance", &[]), "--guidance"),
        (sim("--clamp", &[]), "--clamp"),
        (sim("--schedule", &[]), "--schedule"),
        (sim("--lambda", &[]), "--lambda"),
        (sim("--auto", &["--task", "unconditional"]), "--auto"),
        (args(&["eval", scene, "--task", v]), "--task"),
        (
            args(&["eval", scene, "--task", "behaviour", "--behaviour", v]),
            "--behaviour",
        ),
        (
            args(&["eval", scene, "--task", "conditional", "--baseline", v]),
            "--baseline",
        ),
        (args(&["inspect", scene, "--agents", "--keep", v]), "--keep"),
        (
            args(&["train", "--data", scene, "--out", out, "--setting", v]),
            "--setting",
        ),
        (
            args(&["train", "--data", scene, "--out", out, "--val-town", v]),
            "--val-town",
        ),
        (args(&["demo", "-o", out, "--samples", v]), "--samples"),
        (
            args(&["demo", "-o", out, "--request", v]),
            "is too long for the rules planner",
        ),
        (args(&["bench", v]), "<WHAT>"),
        (
            args(&["inspect", scene, &format!("--{v}")]),
            "unexpected argument",
        ),
        (args(&[v]), "unrecognized subcommand"),
        (ask("--llm"), "--llm"),
        (ask("--model"), "--model"),
        (ask("--llm-url"), "--llm-url"),
        (ask("--max-tokens-field"), "--max-tokens-field"),
        (ask("--context"), "--context"),
        (ask("--temperature"), "--temperature"),
    ];
    for (a, names) in &cases {
        let a: Vec<&str> = a.iter().map(String::as_str).collect();
        let run = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
            .args(&a)
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .env_remove("DRIVESCRIPT_LLM_URL")
            .env_remove("DRIVESCRIPT_LLM_MODEL")
            .output()
            .unwrap();
        let err = String::from_utf8_lossy(&run.stderr).into_owned();
        let shown: Vec<&str> = a.iter().map(|x| &x[..x.len().min(40)]).collect();
        assert!(
            matches!(run.status.code(), Some(1 | 2)),
            "{shown:?}: {:?}\n{err}",
            run.status.code()
        );
        assert!(err.len() < 900, "{shown:?}: {} bytes: {err}", err.len());
        assert!(
            err.contains(names)
                && (err.contains("… (5000 characters)") || err.contains("… (5002 characters)")),
            "{shown:?}: {err}"
        );
        assert!(!err.contains(&"x".repeat(65)), "{shown:?}: {err}");
    }
}

/// `demo --samples 0` (and `simulate`'s sampler flags out of range) name the flag and its
/// range, as `ask --samples 0` does: they said "sampler settings: samples = 0", after the
/// demo had loaded its scene and printed its header.
#[test]
fn sample_counts_out_of_range_name_the_flag_and_its_range() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let yaml = samples().join("yaml/highway_cut_in.yaml");
    let ckpt = std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("data/checkpoint");
    let sim = |flag: &str, v: &str| {
        drivescript(&[
            "simulate",
            s(&yaml),
            "--checkpoint",
            s(&ckpt),
            "-o",
            s(&out),
            flag,
            v,
        ])
    };
    for (run, want) in [
        (
            drivescript(&["demo", "-o", s(&out), "--samples", "0"]),
            "'--samples <SAMPLES>': 0 is not in 1..=1024",
        ),
        (
            drivescript(&["demo", "-o", s(&out), "--samples", "5000"]),
            "'--samples <SAMPLES>': 5000 is not in 1..=1024",
        ),
        (
            sim("--samples", "0"),
            "'--samples <SAMPLES>': 0 is not in 1..=1024",
        ),
        (
            sim("--steps", "1"),
            "'--steps <STEPS>': 1 is not in 2..=1000",
        ),
        (
            sim("--horizon", "0"),
            "'--horizon <HORIZON>': 0 is not in 1..=100000",
        ),
        // It said "width 0 is outside 64..8192 pixels", not which flag.
        (
            drivescript(&["render", s(&yaml), "-o", s(&out), "--width", "0"]),
            "'--width <WIDTH>': 0 is not in 64..=8192",
        ),
    ] {
        let err = String::from_utf8_lossy(&run.stderr).into_owned();
        assert_eq!(run.status.code(), Some(2), "{err}");
        assert!(err.contains(want), "{want}: {err}");
        // Refused before anything is read or written.
        assert!(
            run.stdout.is_empty(),
            "{}",
            String::from_utf8_lossy(&run.stdout)
        );
        assert!(!out.exists());
    }
}

/// `convert`, `render` and `cost --index N` past the source's last scene said "scene 3: the
/// source holds only 1 scenes", naming neither the flag nor the indices there are.
#[test]
fn an_index_past_the_source_names_the_flag_and_the_indices_there_are() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join("x.yaml");
    let pic = dir.path().join("x.svg");
    for args in [
        vec!["convert", s(&scene), "--index", "3", "-o", s(&out)],
        vec!["render", s(&scene), "--index", "3", "-o", s(&pic)],
        vec![
            "cost",
            s(&scene),
            "--index",
            "3",
            "--script",
            "scripts/cut_in.rhai",
            "--param",
            "cutter=2",
            "victim=1",
        ],
    ] {
        let err = fails(&args);
        assert!(
            err.contains("--index 3: ")
                && err.contains(
                    "highway_cut_in.yaml holds 1 scene (give --index 0, or leave it out)"
                ),
            "{args:?}: {err}"
        );
    }
    assert!(!out.exists() && !pic.exists());
}

/// `demo --request` printed the scene and the whole request (12,000 characters of it) before
/// refusing a request the rules planner cannot run.
#[test]
fn demo_refuses_a_request_it_cannot_run_before_printing_anything() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("demo");
    for request in ["", "   ", &"blah".repeat(3000)] {
        let o = drivescript(&["demo", "--request", request, "-o", s(&run)]);
        let out = String::from_utf8_lossy(&o.stdout);
        let err = String::from_utf8_lossy(&o.stderr);
        assert_eq!(o.status.code(), Some(1), "{err}");
        assert!(out.is_empty(), "{out}");
        assert!(
            err.contains("the request is empty")
                || err.contains("does not understand")
                || err.contains("is too long for the rules planner"),
            "{err}"
        );
        assert!(err.len() < 2000, "{} bytes: {err}", err.len());
    }
    assert!(!run.exists());
}

/// A 100,000-character request to the rules planner failed validation as "script.rhai:1:1:
/// limit exceeded: script size", blaming a script the user never wrote (the planner quotes
/// every clause in it); and 60 events overflowed the script at its first repair. A refused
/// request left an empty run directory holding only its lock.
#[test]
fn a_request_too_long_for_the_rules_planner_is_named_as_such() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let run = dir.path().join("run");
    let long = format!(
        "vehicle 1 cuts in front of vehicle 2 {}",
        "x".repeat(100_000)
    );
    let many = vec!["vehicle 1 cuts in front of vehicle 2"; 25].join(", ");
    for (request, what) in [(long, "100037 characters"), (many, "25 events")] {
        let err = fails(&["ask", s(&scene), &request, "--llm", "rules", "-o", s(&run)]);
        assert!(
            err.contains("is too long for the rules planner")
                && err.contains(what)
                && err.contains("at most 2000 characters and 20 events")
                && !err.contains("script size"),
            "{err}"
        );
        assert!(err.len() < 2000, "{} bytes", err.len());
        assert!(!run.exists());
    }
    // Nor does a refused request leave an empty run directory holding only its lock.
    let err = fails(&[
        "ask",
        s(&scene),
        "blah blah",
        "--llm",
        "rules",
        "-o",
        s(&run),
    ]);
    assert!(err.contains("does not understand"), "{err}");
    assert!(!run.exists());
}

/// `render -o x.svg/` said only "Not a directory (os error 20)".
#[test]
fn an_output_path_ending_in_a_slash_is_named_with_the_slip() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let slashed = format!("{}/", dir.path().join("x.svg").display());
    let err = fails(&["render", s(&scene), "-o", &slashed]);
    assert!(
        err.contains(&slashed) && err.contains("trailing slash"),
        "{err}"
    );
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0);
}

/// Shards 0/2 and then 1/3 into one `-o` ran without a word, leaving some scenes in no shard
/// and others in two (each split partitions the scenes only of itself).
#[test]
fn shards_of_another_count_into_one_run_directory_are_refused() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
    let out = dir.path().join("sharded");
    let o = unguided(
        &scenes,
        &out,
        &["--shard", "0/2", "--resume", "--samples", "1"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
    let before = std::fs::read_dir(&out).unwrap().count();
    let o = unguided(
        &scenes,
        &out,
        &["--shard", "1/3", "--resume", "--samples", "1"],
    );
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("holds the shards of this run split 2 ways")
            && err.contains("give --shard I/2"),
        "{err}"
    );
    assert_eq!(std::fs::read_dir(&out).unwrap().count(), before);
    let o = unguided(
        &scenes,
        &out,
        &["--shard", "1/2", "--resume", "--samples", "1"],
    );
    assert!(o.status.success(), "{}", String::from_utf8_lossy(&o.stderr));
}

#[test]
fn an_output_path_under_a_file_names_the_file_in_the_way() {
    // `-o scene.yaml/x.svg` said only "cannot write: File exists (os error 17)" or "Not a
    // directory (os error 20)" of the whole path (issue 32).
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("in.yaml");
    std::fs::copy(samples().join("yaml/highway_cut_in.yaml"), &scene).unwrap();
    let under = |rest: &str| dir.path().join("in.yaml").join(rest);
    for args in [
        vec!["render", s(&scene), "-o", s(&under("x.svg"))],
        vec!["render", s(&scene), "-o", s(&under("a/b/x.png"))],
        vec!["convert", s(&scene), "-o", s(&under("x.json"))],
        vec![
            "simulate",
            s(&scene),
            "--checkpoint",
            "data/checkpoint",
            "--samples",
            "1",
            "-o",
            s(&under("run")),
        ],
    ] {
        let err = fails(&args);
        assert!(
            err.contains(&format!("{} is a file, not a directory", scene.display()))
                && !err.contains("os error"),
            "{args:?}: {err}"
        );
    }
    assert_eq!(
        std::fs::read(&scene).unwrap(),
        std::fs::read(samples().join("yaml/highway_cut_in.yaml")).unwrap()
    );
}

/// `test-scripts` on `DIR/x.test.yaml`, written as a test file of `scripts/SCRIPT` whose
/// `cases:` list is `cases` (YAML).
fn run_test_file(dir: &std::path::Path, script: &str, cases: &str) -> std::process::Output {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let t = dir.join("x.test.yaml");
    std::fs::write(
        &t,
        format!(
            "script: {}\ncases:\n{cases}",
            s(&root.join("scripts").join(script))
        ),
    )
    .unwrap();
    common::drivescript(&["test-scripts", s(&t)])
}

/// `test-scripts` on one case of `scripts/SCRIPT` on the highway scene with `params` and the
/// expectation `expect`, which must fail: exit 1, and what it printed.
fn failing_case(script: &str, params: &str, expect: &str) -> String {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let dir = tempfile::tempdir().unwrap();
    let out = run_test_file(
        dir.path(),
        script,
        &format!(
            "  - name: wrong on purpose\n    scene: {}\n    params: {{{params}}}\n    expect: {{{expect}}}\n",
            s(&root.join("scripts/scenes/highway.yaml"))
        ),
    );
    assert_eq!(out.status.code(), Some(1));
    String::from_utf8_lossy(&out.stdout).into_owned()
}

#[test]
fn a_failed_largest_term_expectation_names_the_largest_plainly() {
    // It said `(it is Some("ends_in_victim_lane"))`, Rust's debug form (issue 32).
    let text = failing_case(
        "cut_in.rhai",
        "cutter: 2, victim: 1",
        "largest_term: no_contact",
    );
    assert!(
        text.contains("FAILED largest term is no_contact (it is ends_in_victim_lane)")
            && !text.contains("Some("),
        "{text}"
    );
}

#[test]
fn a_second_train_into_one_out_is_refused_while_the_first_runs() {
    // Both trained, rewrote each other's window cache and replaced each other's checkpoint
    // files in turn, without a word (issue 32).
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("ck");
    let args = |seed: &str| {
        vec![
            "train".to_string(),
            "--data".into(),
            s(&samples().join("commonroad")).into(),
            "--out".into(),
            s(&out).into(),
            "--steps".into(),
            "1000000".into(),
            "--eval-every".into(),
            "1000000".into(),
            "--seed".into(),
            seed.into(),
        ]
    };
    let mut first = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
        .args(args("1"))
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    // The windows are cut after the lock is taken.
    let t0 = std::time::Instant::now();
    while !out.join("windows/train.windows").exists() {
        assert!(t0.elapsed().as_secs() < 120, "the first run made no cache");
        std::thread::sleep(std::time::Duration::from_millis(50));
    }
    let second: Vec<String> = args("2");
    let second: Vec<&str> = second.iter().map(String::as_str).collect();
    let err = fails(&second);
    let _ = first.kill();
    let _ = first.wait();
    assert!(
        err.contains("another drivescript train is writing its checkpoint there"),
        "{err}"
    );
}

/// A float flag written beyond the largest float is refused as written: it read as infinity
/// and the flag's range check said `inf`, a value nobody typed (`--lambda inf: must be 0 to
/// 1000` for `--lambda 1e400`) (issue 32).
#[test]
fn float_flags_beyond_the_largest_float_are_refused_as_written() {
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let scene = s(&scene);
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let out = s(&out);
    let sim = |flag: &'static str| -> Vec<&str> {
        vec![
            "simulate",
            scene,
            "--checkpoint",
            "data/checkpoint",
            flag,
            "-o",
            out,
        ]
    };
    let ask =
        |flag: &'static str| -> Vec<&str> { vec!["ask", scene, "a request", "-o", out, flag] };
    let train =
        |flag: &'static str| -> Vec<&str> { vec!["train", "--data", scene, "--out", out, flag] };
    let cases = [
        sim("--lambda=-1e400"),
        sim("--realism=-1e400"),
        sim("--known-weight=-1e400"),
        sim("--script-budget=-1e400"),
        ask("--temperature=-1e400"),
        ask("--llm-timeout=-1e400"),
        ask("--reply-deadline=-1e400"),
        ask("--backoff=-1e400"),
        ask("--backoff-max=-1e400"),
        ask("--tolerance=-1e400"),
        ask("--script-budget=-1e400"),
        train("--lr=-1e400"),
        train("--ema-half-life=-1e400"),
        train("--scale-cap=-1e400"),
        train("--p-mean=-1e400"),
        vec!["bench", "io", "--seconds=-1e400"],
    ];
    for args in cases {
        let run = drivescript(&args);
        let err = String::from_utf8_lossy(&run.stderr);
        assert_eq!(run.status.code(), Some(2), "{args:?}: {err}");
        assert!(
            err.contains("-1e400 is beyond the largest number")
                && !err.contains("inf:")
                && !err.contains("= inf"),
            "{args:?}: {err}"
        );
    }
    assert!(!dir.path().join("out").exists());
    // Infinity typed as such still reaches the flag's own check.
    let err = fails(&["bench", "io", "--seconds", "inf"]);
    assert!(err.contains("--seconds inf"), "{err}");
}

/// A training noise setting whose levels are past what f32 holds (`--p-mean 700`, `-50`,
/// `--p-std 50`) was taken, the windows cut, and the run stopped at its first step with
/// "training loss is NaN ... training diverged (lower --lr)", blaming a flag not given. It is
/// refused before any data is read, naming the flag and its range.
#[test]
fn training_noise_levels_past_f32_are_refused_naming_the_flag() {
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    for (flag, value) in [("--p-mean", "700"), ("--p-mean", "-50"), ("--p-std", "50")] {
        let arg = format!("{flag}={value}");
        let err = fails(&["train", "--data", s(&scene), "--out", s(&out), &arg]);
        assert!(
            err.contains(&format!("{flag}: ")) && err.contains("must be") && !err.contains("--lr"),
            "{arg}: {err}"
        );
        assert!(!err.contains("windows"), "{arg}: {err}");
    }
    assert!(!out.exists());
}

#[test]
fn ask_repeats_an_out_of_range_number_as_it_was_typed() {
    // `--tolerance -1` was told "--tolerance -1.0" (Rust's Debug form of the float).
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let scene = samples().join("yaml/highway_cut_in.yaml");
    for (flag, typed) in [
        ("--tolerance", "-1"),
        ("--temperature", "3"),
        ("--llm-timeout", "0"),
        ("--reply-deadline", "100000"),
        ("--backoff", "700"),
        ("--backoff-max", "5000"),
    ] {
        let arg = format!("{flag}={typed}");
        let err = fails(&["ask", s(&scene), "a request", "-o", s(&out), &arg]);
        assert!(err.contains(&format!("{flag} {typed}: must")), "{err}");
        assert!(!err.contains(".0:"), "{err}");
    }
    assert!(!out.exists());
}

/// Rollouts of several samples scored with the default `--samples 1` gave the figures of the
/// first sample alone, and said nothing.
#[test]
fn eval_refuses_rollouts_holding_more_samples_than_it_was_told() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let r = dir.path().join("r");
    std::fs::create_dir(&r).unwrap();
    for k in 0..3 {
        ok(&[
            "convert",
            s(&scene),
            "-o",
            s(&r.join(format!("highway-cut-in_{k}.json"))),
        ]);
    }
    for samples in ["1", "2"] {
        let err = fails(&[
            "eval",
            s(&scene),
            "--task",
            "conditional",
            "--rollouts",
            s(&r),
            "--samples",
            samples,
        ]);
        assert!(
            err.contains(&format!(
                "highway-cut-in_{samples}.json: the rollouts hold more samples of scene \
                 highway-cut-in than --samples {samples}"
            )),
            "{err}"
        );
    }
    let out = ok(&[
        "eval",
        s(&scene),
        "--task",
        "conditional",
        "--rollouts",
        s(&r),
        "--samples",
        "3",
    ]);
    assert!(out.contains("| rollouts in "), "{out}");
    // An unnumbered rollout beside them: with --samples 1 it was scored alone and the three
    // samples left out without a word.
    ok(&[
        "convert",
        s(&scene),
        "-o",
        s(&r.join("highway-cut-in.json")),
    ]);
    let err = fails(&[
        "eval",
        s(&scene),
        "--task",
        "conditional",
        "--rollouts",
        s(&r),
    ]);
    assert!(
        err.contains("the rollouts hold both highway-cut-in.json and numbered samples"),
        "{err}"
    );
}

/// A negative number after a flag was read as the flag `-1`: "unexpected argument '-1' found",
/// with the tip to write `-- -1` (which passes it as a scene), for every flag not marked to
/// take one (`--lambda`, `--realism`, `--lr`, `--index`, ...); `--script-budget -0` was
/// repeated as Rust writes the float ("-0.0").
#[test]
fn a_negative_number_is_the_flag_s_value_and_its_check_names_it() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join("out");
    let sim = [
        "simulate",
        s(&scene),
        "--checkpoint",
        "data/checkpoint",
        "-o",
        s(&out),
    ];
    let train = ["train", "--data", "scripts/scenes", "--out", s(&out)];
    for (command, flag, v, says) in [
        (&sim[..], "--lambda", "-1", "--lambda -1: must be 0 to 1000"),
        (
            &sim[..],
            "--realism",
            "-2",
            "--realism -2: must be 0 to 1000",
        ),
        (
            &sim[..],
            "--known-weight",
            "-1",
            "--known-weight -1: must be 0 to 1000",
        ),
        (
            &sim[..],
            "--script-budget",
            "-0",
            "--script-budget -0: must be more than 0",
        ),
        (&train[..], "--lr", "-1", "--lr: lr = -1: must be positive"),
        (
            &train[..],
            "--scale-cap",
            "-1",
            "--scale-cap: scale_cap = -1",
        ),
        (
            &train[..],
            "--across-weight",
            "-3",
            "--across-weight: across_weight = -3",
        ),
        (
            &train[..],
            "--ema-half-life",
            "-5",
            "--ema-half-life: ema_half_life = -5",
        ),
    ] {
        let mut args = command.to_vec();
        args.extend([flag, v]);
        let err = fails(&args);
        assert!(err.contains(says), "{flag} {v}: {err}");
        assert!(!err.contains("unexpected argument"), "{err}");
    }
    // A count is no number below 0: clap's own refusal names the flag and the value.
    let o = drivescript(&["render", s(&scene), "--index", "-1", "-o", s(&out)]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(2), "{err}");
    assert!(err.contains("invalid value '-1' for '--index"), "{err}");
    assert!(!out.exists());
}

/// A GIF of thousands of frames drew for half a minute without a word; one of a few frames
/// still says nothing.
#[test]
fn a_long_gif_says_how_many_frames_are_drawn_as_it_goes() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("long.yaml");
    std::fs::write(
        &scene,
        "steps: 250\ncurrent_step: 10\nroad: {lanes: 2, lane_width: 3.6, length: 300}\nagents:\n  - {id: 1, lane: 0, s: 50, speed: 1}\n",
    )
    .unwrap();
    let gif = dir.path().join("long.gif");
    let o = drivescript(&["render", s(&scene), "-o", s(&gif), "--width", "64"]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert!(o.status.success(), "{err}");
    assert!(
        err.contains("drew 25 of 250 frames") && err.contains("drew 250 of 250 frames"),
        "{err}"
    );
    assert_eq!(err.lines().count(), 10, "{err}");
    let short = samples().join("yaml/highway_cut_in.yaml");
    let o = drivescript(&["render", s(&short), "-o", s(&gif), "--width", "64"]);
    assert!(o.status.success() && o.stderr.is_empty(), "{o:?}");
}

/// A scene whose rollouts failed was counted in the horizon line ("(2 scenes)") under a
/// table of the one scene scored.
#[test]
fn the_horizon_line_counts_only_the_scenes_scored() {
    let dir = tempfile::tempdir().unwrap();
    let r = dir.path().join("r");
    std::fs::create_dir(&r).unwrap();
    let yaml = samples().join("yaml");
    ok(&[
        "convert",
        s(&yaml.join("highway_cut_in.yaml")),
        "-o",
        s(&r.join("highway-cut-in.json")),
    ]);
    let o = drivescript(&[
        "eval",
        s(&yaml),
        "--task",
        "conditional",
        "--rollouts",
        s(&r),
    ]);
    let (out, err) = (
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr),
    );
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("missing rollout for scene curved-two-lanes"),
        "{err}"
    );
    let line = out
        .lines()
        .find(|l| l.starts_with("horizon ("))
        .unwrap_or_default();
    assert!(
        line.contains("the rollouts' own (1 scene)") && line.matches(" steps, ").count() == 1,
        "{out}"
    );
}

/// `eval --json DIR` ran the whole evaluation, printed its table and then failed writing the
/// file (an evaluation can take hours); a directory named as a picture was drawn first too.
#[test]
fn an_output_that_is_a_directory_is_refused_before_the_work() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let json = dir.path().join("results.json");
    std::fs::create_dir(&json).unwrap();
    let o = drivescript(&[
        "eval",
        s(&scene),
        "--task",
        "conditional",
        "--baseline",
        "log",
        "--json",
        s(&json),
    ]);
    let err = String::from_utf8_lossy(&o.stderr);
    assert_eq!(o.status.code(), Some(1), "{err}");
    assert!(
        err.contains("results.json: --json: is a directory: name a file to write"),
        "{err}"
    );
    assert!(
        o.stdout.is_empty(),
        "{}",
        String::from_utf8_lossy(&o.stdout)
    );
    let svg = dir.path().join("picture.svg");
    std::fs::create_dir(&svg).unwrap();
    let err = fails(&["render", s(&scene), "-o", s(&svg)]);
    assert!(err.contains("picture.svg: -o: is a directory"), "{err}");
}

/// A demo whose scene lacks the request's agents samples no round, and said it wrote
/// final.gif and final.rhai all the same.
#[test]
fn a_demo_that_samples_nothing_names_only_what_it_wrote() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("two.yaml");
    std::fs::write(
        &scene,
        "steps: 51\ncurrent_step: 10\nroad: {lanes: 2, lane_width: 3.6, length: 300}\nagents:\n  - {id: 1, lane: 0, s: 50, speed: 20}\n  - {id: 2, lane: 1, s: 60, speed: 20}\n",
    )
    .unwrap();
    let out = dir.path().join("demo");
    let o = drivescript(&[
        "demo",
        "--scene",
        s(&scene),
        "-o",
        s(&out),
        "--samples",
        "1",
    ]);
    let text = String::from_utf8_lossy(&o.stdout);
    assert_eq!(o.status.code(), Some(2), "{text}");
    assert!(!out.join("final.gif").exists());
    assert!(
        !text.contains("final.gif") && text.contains("report.md and"),
        "{text}"
    );
}

/// A numbered sample past a missing one was left out unsaid: with `ID_1.json` gone,
/// `--samples 1` scored `ID_0.json` alone beside an `ID_2.json`, and an unnumbered rollout
/// beside `ID_1.json` (no `ID_0.json`) was scored alone.
#[test]
fn eval_refuses_a_numbered_sample_past_a_missing_one() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let r = dir.path().join("r");
    std::fs::create_dir(&r).unwrap();
    for name in ["highway-cut-in_0.json", "highway-cut-in_2.json"] {
        ok(&["convert", s(&scene), "-o", s(&r.join(name))]);
    }
    let eval = |extra: &[&str]| {
        let mut a = vec![
            "eval",
            s(&scene),
            "--task",
            "conditional",
            "--rollouts",
            s(&r),
        ];
        a.extend_from_slice(extra);
        fails(&a)
    };
    let err = eval(&[]);
    assert!(
        err.contains("highway-cut-in_2.json: the rollouts hold more samples of scene"),
        "{err}"
    );
    // With the number the run made, the gap is named.
    let err = eval(&["--samples", "3"]);
    assert!(
        err.contains("highway-cut-in_1.json: missing rollout for scene highway-cut-in"),
        "{err}"
    );
    std::fs::remove_file(r.join("highway-cut-in_0.json")).unwrap();
    ok(&[
        "convert",
        s(&scene),
        "-o",
        s(&r.join("highway-cut-in.json")),
    ]);
    let err = eval(&[]);
    assert!(
        err.contains("highway-cut-in_2.json: the rollouts hold both highway-cut-in.json"),
        "{err}"
    );
}

/// `wrote PATH` printed an output name's escape sequence raw (`-o $'x\e[2J.svg'` cleared the
/// screen), where every error about the same name escapes it.
#[test]
fn the_wrote_line_escapes_what_a_terminal_would_act_on() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    for name in ["x\u{1b}[2J.svg", "r\u{202e}.json"] {
        let out = dir.path().join(name);
        let args = if name.ends_with(".svg") {
            vec!["render", s(&scene), "-o", s(&out)]
        } else {
            vec!["convert", s(&scene), "-o", s(&out)]
        };
        let printed = ok(&args);
        assert!(out.exists(), "{name:?}");
        assert!(
            !printed.contains('\u{1b}') && !printed.contains('\u{202e}'),
            "{printed:?}"
        );
        assert!(
            printed.contains("\\u{001B}[2J.svg") || printed.contains("r\\u{202E}.json"),
            "{printed:?}"
        );
    }
    // simulate's `wrote N scenes to DIR`, the same for a line break that forged a line.
    let out = dir.path().join("o\u{1b}[2J\nerror: forged");
    let printed = ok(&simulate_args(
        s(&scene),
        "data/checkpoint",
        &["--steps", "10"],
        s(&out),
    ));
    assert!(out.join("highway-cut-in_0.json").exists(), "{printed}");
    assert!(
        !printed.contains('\u{1b}')
            && !printed.contains("\nerror: forged")
            && printed.contains("o\\u{001B}[2J\\u{000A}error: forged"),
        "{printed:?}"
    );
}

/// `render -o .svg` names a hidden file with no extension, and was told only "unknown picture
/// format; use .svg, .png or .gif".
#[test]
fn an_output_named_only_by_its_extension_is_told_so() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join(".svg");
    let err = fails(&["render", s(&scene), "-o", s(&out)]);
    assert!(
        err.contains(".svg: the name is only an extension") && err.contains("e.g. out.svg"),
        "{err}"
    );
    assert!(!out.exists());
}

/// Runs `test-scripts` on a one-case file for scripts/follow.rhai on highway_crash (`case`:
/// the case's keys after `scene:`, YAML); returns the exit code and stdout + stderr.
fn follow_case(dir: &std::path::Path, case: &str) -> (Option<i32>, String) {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR"));
    let out = run_test_file(
        dir,
        "follow.rhai",
        &format!(
            "  - name: c\n    scene: {}\n{case}",
            s(&root.join("scripts/scenes/highway_crash.yaml"))
        ),
    );
    let text = String::from_utf8_lossy(&out.stdout).into_owned()
        + String::from_utf8_lossy(&out.stderr).as_ref();
    (out.status.code(), text)
}

/// An edit that cannot change the candidate: a `freeze` after another edit of the same agent
/// undid that edit, and a shift, lateral move or sway of size 0 moved nothing; each case ran
/// on a future its file did not describe, and passed.
#[test]
fn test_scripts_refuses_edits_that_are_undone_or_move_nothing() {
    let dir = tempfile::tempdir().unwrap();
    for (edits, want) in [
        (
            "[{agent: 3, shift: [1, 0]}, {agent: 3, freeze: true}]",
            "edit 2 (agent 3): `freeze` holds the current state for the whole future, so edit 1 of the same agent would be undone",
        ),
        ("[{agent: 3, shift: [0, 0]}]", "edit 1 (agent 3): it changes nothing"),
        ("[{agent: 3, sway: [0, 2]}]", "edit 1 (agent 3): it changes nothing"),
        ("[{agent: 3, lateral: 0.0, ramp: 1}]", "it changes nothing"),
    ] {
        let (code, text) = follow_case(
            dir.path(),
            &format!("    params: {{follower: 3, leader: 1, gap: 10}}\n    edits: {edits}\n    expect: {{total_above: 0}}\n"),
        );
        assert_eq!(code, Some(1), "{edits}: {text}");
        assert!(text.contains(want) && text.contains("0 passed"), "{edits}: {text}");
    }
    // A freeze first, then a shift of the frozen car, is an edit of its own.
    let (_, text) = follow_case(
        dir.path(),
        "    params: {follower: 3, leader: 1, gap: 10}\n    edits: [{agent: 3, freeze: true}, {agent: 3, shift: [-20, 0]}]\n    expect: {terms_above: {keeps_gap: 1}}\n",
    );
    assert!(text.contains("1 passed, 0 failed"), "{text}");
}

/// `params: {gapp: 30}` (for `gap`) ran the case on the script's default gap, and it passed;
/// `cost --param gapp=30` refuses the same typo. Thresholds no total can meet (`total_below:
/// 1, total_above: 2`) failed the case whatever the script did.
#[test]
fn test_scripts_refuses_a_parameter_the_script_never_reads_and_thresholds_that_exclude_each_other()
{
    let dir = tempfile::tempdir().unwrap();
    for (params, expect, want) in [
        (
            "{follower: 3, leader: 1, gapp: 30}",
            "{total_below: 0.01}",
            "parameter \"gapp\": no script reads it",
        ),
        (
            "{follower: 3, leader: 1}",
            "{total_below: 1, total_above: 2}",
            "the total must be at most 1 and above 2: no value is both",
        ),
        (
            "{follower: 3, leader: 1}",
            "{terms_below: {keeps_gap: 0.5}, terms_above: {keeps_gap: 0.5}}",
            "term keeps_gap must be at most 0.5 and above 0.5",
        ),
    ] {
        let (code, text) = follow_case(
            dir.path(),
            &format!("    params: {params}\n    expect: {expect}\n"),
        );
        assert_eq!(code, Some(1), "{params}: {text}");
        assert!(
            text.contains(want) && text.contains("0 passed"),
            "{params}: {text}"
        );
    }
}

/// A scene whose id cannot name an output file stopped `simulate` over a directory of scenes
/// with "scenario id \"a/b\" cannot name an output file", naming no file.
#[test]
fn an_id_that_cannot_name_an_output_file_names_the_scene_file_holding_it() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = dir.path().join("scenes");
    std::fs::create_dir(&scenes).unwrap();
    let yaml = scenes.join("odd.yaml");
    std::fs::write(
        &yaml,
        "scenario_id: a/b\ndt: 0.1\nsteps: 60\ncurrent_step: 10\nroad: {lanes: 1, length: 300}\nagents:\n  - {id: 1, lane: 0, s: 30, speed: 10}\n",
    )
    .unwrap();
    let err = fails(&[
        "simulate",
        s(&scenes),
        "--checkpoint",
        "data/checkpoint",
        "--samples",
        "1",
        "-o",
        s(&dir.path().join("out")),
    ]);
    assert!(
        err.contains(&format!(
            "{}: scenario_id: scenario id \"a/b\" cannot name an output file",
            s(&yaml)
        )),
        "{err}"
    );
}

/// `train --val-town` given for many towns no scene is in repeated every one of them: 3,000
/// gave a message of 24 KB. The first twelve are named and the rest counted.
#[test]
fn many_held_out_towns_no_scene_is_in_are_counted_not_all_repeated() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("out");
    let towns: Vec<String> = (0..100).map(|i| format!("--val-town=T{i:03}")).collect();
    let mut args = vec!["train", "--urban", "scripts/scenes", "--out", s(&out)];
    args.extend(towns.iter().map(String::as_str));
    let err = fails(&args);
    assert!(
        err.contains("--val-town \"T000\" \"T001\"") && err.contains("\"T011\" and 88 more:"),
        "{err}"
    );
    assert!(!err.contains("T012"), "{err}");
    assert!(err.len() < 1500, "{} bytes: {err}", err.len());
}

/// `train --out C`, where C is another run's window cache (`--cache C`), wrote the checkpoint
/// among its windows, and that run's next start refused its cache as holding files not its
/// own. It is refused before anything is read or written.
#[test]
fn a_checkpoint_directory_that_is_a_window_cache_is_refused() {
    let dir = tempfile::tempdir().unwrap();
    let cache = dir.path().join("cache");
    std::fs::create_dir(&cache).unwrap();
    std::fs::write(cache.join("train.windows"), b"DSWIN01\n").unwrap();
    let err = fails(&[
        "train",
        "--data",
        "scripts/scenes",
        "--out",
        s(&cache),
        "--steps",
        "2",
    ]);
    assert!(
        err.contains("train.windows but no config.json: it is a window cache (--cache)"),
        "{err}"
    );
    let left: Vec<_> = std::fs::read_dir(&cache).unwrap().collect();
    assert_eq!(left.len(), 1, "{err}");
}

/// Float flags far past any sensible value (`--ema-half-life 1e308`, `--tolerance 1e308`,
/// `--lr 1e-300`) were taken: a moving average that never left the first weights, a tolerance
/// every sample met, a step rounded away in every weight. Each is refused before anything is
/// read or written, naming the flag, in a few characters.
#[test]
fn absurdly_large_float_flags_are_refused_naming_the_flag() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join("yaml/highway_cut_in.yaml");
    let out = dir.path().join("out");
    let train = ["train", "--data", "scripts/scenes", "--out", s(&out)];
    let ask = ["ask", s(&scene), "a request", "-o", s(&out)];
    for (command, flag, says) in [
        (
            &train[..],
            "--ema-half-life",
            "--ema-half-life: ema_half_life = 1e308: must be 0",
        ),
        (
            &ask[..],
            "--tolerance",
            "--tolerance 1e308: must be finite and not negative, at most 1000",
        ),
    ] {
        let mut args = command.to_vec();
        args.extend([flag, "1e308"]);
        let err = fails(&args);
        assert!(err.contains(says), "{flag}: {err}");
        assert!(err.len() < 400, "{flag}: {err}");
    }
    // As small: a rate f32 weights round away trained nothing, exit 0.
    let mut args = train.to_vec();
    args.extend(["--lr", "1e-300"]);
    let err = fails(&args);
    assert!(
        err.contains("--lr: lr = 1e-300: must be at least 1e-8"),
        "{err}"
    );
    // The route frame beside route times was refused naming a setting, not the flag.
    let mut args = train.to_vec();
    args.extend(["--route-frame", "--route-times", "4"]);
    let err = fails(&args);
    assert!(
        err.contains("training settings: --route-frame: window.route_frame with route_times"),
        "{err}"
    );
    assert!(!out.exists());
}

/// A `train` refused after its --out was made (a held-out town no scene is in) left an empty
/// OUT/windows behind; a refused run leaves nothing it made.
#[test]
fn a_refused_train_leaves_nothing_it_made() {
    let dir = tempfile::tempdir().unwrap();
    let out = dir.path().join("deep/out");
    let err = fails(&[
        "train",
        "--urban",
        "scripts/scenes",
        "--val-town",
        "DEU_Atlantis",
        "--out",
        s(&out),
        "--steps",
        "2",
    ]);
    assert!(err.contains("--val-town \"DEU_Atlantis\""), "{err}");
    assert_eq!(std::fs::read_dir(dir.path()).unwrap().count(), 0, "{err}");
}

/// `bench --seconds 1e9` was repeated as "--seconds 1000000000.0", Rust's debug form of the
/// float, not as it was typed.
#[test]
fn bench_repeats_an_out_of_range_seconds_as_it_was_typed() {
    for (typed, shown) in [("1e9", "1e9"), ("4000", "4000"), ("0.01", "0.01")] {
        let err = fails(&["bench", "io", "--seconds", typed]);
        assert!(
            err.contains(&format!("--seconds {shown}: give 0.05 to 3600")),
            "{typed}: {err}"
        );
        assert!(!err.contains(".0:"), "{err}");
    }
}

/// Labels were placed checking every box and every label already placed: time growing with
/// the square of the agents (a PNG of 20,000 parked cars took half a minute; a `simulate` of
/// 20,000 did not finish its GIF). A picture of 40,000 is drawn in seconds.
#[test]
fn a_picture_of_tens_of_thousands_of_agents_is_drawn_in_seconds() {
    let dir = tempfile::tempdir().unwrap();
    let mut yaml = String::from(
        "scenario_id: crowd\ndt: 0.1\nsteps: 11\ncurrent_step: 10\nroad: {lanes: 8, length: \
         40000}\nagents:\n",
    );
    for lane in 0..8 {
        for k in 0..5000 {
            let id = lane * 5000 + k + 1;
            yaml += &format!("  - {{id: {id}, lane: {lane}, s: {}}}\n", 10 + k * 8);
        }
    }
    let scene = dir.path().join("crowd.yaml");
    std::fs::write(&scene, yaml).unwrap();
    let png = dir.path().join("crowd.png");
    let t0 = std::time::Instant::now();
    ok(&["render", s(&scene), "-o", s(&png)]);
    let took = t0.elapsed().as_secs_f64();
    assert!(png.exists());
    assert!(took < 10.0, "{took:.1} s");
}
