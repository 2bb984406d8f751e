//! The LLM loop against a real HTTP server on 127.0.0.1 with scripted replies (no network),
//! the manual backend's files, `--resume`, and the rules planner, through the library's
//! client and through `drivescript ask`.

mod common;

use std::path::Path;
use std::process::Output;
use std::time::{Duration, Instant};

use common::llm_server::{refused_url, Canned, Server};
use common::{s, samples};
use drivescript::llm::client::ClientEvent;
use drivescript::llm::{HttpClient, HttpConfig, LlmError, Message};

fn client(url: &str) -> HttpClient {
    let mut c = HttpConfig::new(url, "test-model");
    c.backoff = Duration::from_millis(20);
    c.read_timeout = Duration::from_secs(20);
    HttpClient::new(c).unwrap()
}

fn ask_one(c: &HttpClient) -> Result<drivescript::llm::client::Exchange, LlmError> {
    c.complete(&[Message::new("user", "hello")])
}

#[test]
fn a_completion_sends_the_model_temperature_key_and_reads_usage() {
    let srv = Server::start(vec![Canned::chat("hi there")]);
    let mut cfg = HttpConfig::new(&srv.url, "qwen2.5-coder:32b");
    cfg.key = Some("sk-test-secret".into());
    let ex = HttpClient::new(cfg)
        .unwrap()
        .complete(&[Message::new("user", "x")])
        .unwrap();
    assert_eq!(ex.reply, "hi there");
    assert_eq!(ex.usage.unwrap().completion_tokens, 200);
    let r = &srv.received()[0];
    assert_eq!(
        (r.method.as_str(), r.path.as_str()),
        ("POST", "/v1/chat/completions")
    );
    assert_eq!(r.header("authorization"), Some("Bearer sk-test-secret"));
    let body = r.json();
    assert_eq!(body["model"], "qwen2.5-coder:32b");
    assert_eq!(body["temperature"], 0.2);
    assert_eq!(body["max_tokens"], 4096);
    // The record keeps the body, never the key.
    assert!(!serde_json::to_string(&ex)
        .unwrap()
        .contains("sk-test-secret"));
}

#[test]
fn garbage_json_and_string_error_bodies_are_one_line_errors() {
    let srv = Server::start(vec![
        Canned::raw(200, "<html>proxy error</html>"),
        Canned::raw(400, r#"{"error": "context length exceeded"}"#),
        Canned::raw(200, r#"{"choices": []}"#),
    ]);
    let c = client(&srv.url);
    let e = ask_one(&c).unwrap_err().to_string();
    assert!(e.contains("not JSON") && e.contains("<html>"), "{e}");
    let e = ask_one(&c).unwrap_err().to_string();
    assert!(
        e.contains("HTTP 400") && e.contains("context length exceeded"),
        "{e}"
    );
    let e = ask_one(&c).unwrap_err().to_string();
    assert!(e.contains("\"choices\" is empty"), "{e}");
}

#[test]
fn rate_limits_are_retried_honouring_retry_after() {
    let srv = Server::start(vec![
        Canned::raw(
            429,
            r#"{"error": {"message": "rate limited", "code": 429}}"#,
        )
        .header("Retry-After", "1"),
        Canned::chat("after the wait"),
        Canned::raw(
            429,
            r#"{"error": {"message": "slow down", "code": "rate_limit"}}"#,
        ),
        Canned::chat("after backoff"),
    ]);
    let c = client(&srv.url);
    let t0 = Instant::now();
    let ex = ask_one(&c).unwrap();
    assert_eq!(ex.reply, "after the wait");
    assert!(
        t0.elapsed() >= Duration::from_millis(950),
        "Retry-After was not honoured"
    );
    assert_eq!(ex.retries.len(), 1);
    assert!(ex.retries[0].contains("Retry-After"), "{:?}", ex.retries);
    let t0 = Instant::now();
    let ex = ask_one(&c).unwrap();
    assert_eq!(ex.reply, "after backoff");
    assert!(t0.elapsed() < Duration::from_millis(900));
    assert!(
        ex.retries[0].contains("slow down (rate_limit)"),
        "{:?}",
        ex.retries
    );
}

#[test]
fn server_errors_give_up_after_the_attempts_with_the_message() {
    let e500 = Canned::raw(
        500,
        r#"{"error": {"message": "CUDA out of memory", "code": null}}"#,
    );
    let srv = Server::start(vec![e500.clone(), e500.clone(), e500]);
    let e = ask_one(&client(&srv.url)).unwrap_err();
    assert!(
        matches!(
            e,
            LlmError::Status {
                status: 500,
                attempts: 3,
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("CUDA out of memory"), "{e}");
    assert_eq!(srv.received().len(), 3);
}

#[test]
fn timeouts_refusals_bad_keys_and_unknown_models_say_what_to_do() {
    let srv = Server::start(vec![Canned::chat("late").after(Duration::from_secs(3))]);
    let mut cfg = HttpConfig::new(&srv.url, "m");
    cfg.read_timeout = Duration::from_millis(300);
    let e = ask_one(&HttpClient::new(cfg).unwrap()).unwrap_err();
    assert!(
        matches!(
            e,
            LlmError::Timeout {
                connecting: false,
                ..
            }
        ),
        "{e}"
    );
    assert!(e.to_string().contains("--llm-timeout"), "{e}");

    let e = ask_one(&client(&refused_url())).unwrap_err();
    assert!(matches!(e, LlmError::Connect { .. }), "{e}");
    assert!(e.to_string().contains("ollama serve"), "{e}");

    let srv = Server::start(vec![
        Canned::raw(
            401,
            r#"{"error": {"message": "Incorrect API key provided", "code": "invalid_api_key"}}"#,
        ),
        Canned::raw(404, r#"{"error": {"message": "model 'nope' not found"}}"#),
    ]);
    let e = ask_one(&client(&srv.url)).unwrap_err();
    assert!(matches!(e, LlmError::Auth { status: 401, .. }), "{e}");
    assert!(e.to_string().contains("DRIVESCRIPT_LLM_KEY"), "{e}");
    let e = ask_one(&client(&srv.url)).unwrap_err().to_string();
    assert!(
        e.contains("404") && e.contains("test-model") && e.contains("/v1"),
        "{e}"
    );
    // Neither is retried.
    assert_eq!(srv.received().len(), 2);
}

// ---- drivescript ask, end to end ----

const SCENE: &str = "commonroad/USA_US101-3_3_T-1.xml";
const REQUEST: &str = "vehicle 401 cuts in front of vehicle 399";

fn cut_in_script(cutter: i64, victim: i64) -> String {
    std::fs::read_to_string(Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/cut_in.rhai"))
        .unwrap()
        .replace("param(\"cutter\")", &cutter.to_string())
        .replace("param(\"victim\")", &victim.to_string())
}

/// A script that pulls nobody: the cut-in checker fails on its samples. Its term is 0 on every
/// plausible sample but wakes above 35 m/s, so validation's probes do not refuse it as dead.
const IDLE: &str = "let a = agent(401);\nterm(\"idle\", relu(a.speed - 35.0).mean());\n";

/// `ask SCENE REQUEST -o dir` with `extra` flags.
fn ask_cut_in(dir: &Path, extra: &[&str], url: Option<&str>) -> Output {
    let scene = samples().join(SCENE);
    ask(&[&[s(&scene), REQUEST, "-o", s(dir)], extra].concat(), url)
}

fn reply(script: &str) -> String {
    format!("1. Events: one cut-in.\n2. Agents: 401 acts.\n\n```rhai\n{script}```\n")
}

fn ask(args: &[&str], url: Option<&str>) -> Output {
    let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"));
    cmd.arg("ask")
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env_remove("DRIVESCRIPT_LLM_URL")
        .env_remove("DRIVESCRIPT_LLM_MODEL")
        .env("DRIVESCRIPT_LLM_KEY", "sk-test-secret");
    if let Some(u) = url {
        cmd.env("DRIVESCRIPT_LLM_URL", u)
            .env("DRIVESCRIPT_LLM_MODEL", "test-model")
            .args(["--backoff", "0.02"]);
    }
    cmd.output().expect("the binary runs")
}

fn text(o: &Output) -> String {
    format!(
        "{}{}",
        String::from_utf8_lossy(&o.stdout),
        String::from_utf8_lossy(&o.stderr)
    )
}

/// No file of the run holds the key.
fn assert_no_key(dir: &Path) {
    for e in walk(dir) {
        let bytes = std::fs::read(&e).unwrap();
        assert!(
            !String::from_utf8_lossy(&bytes).contains("sk-test-secret"),
            "{} holds the key",
            e.display()
        );
    }
}

fn walk(dir: &Path) -> Vec<std::path::PathBuf> {
    let mut out = Vec::new();
    for e in std::fs::read_dir(dir).unwrap() {
        let p = e.unwrap().path();
        if p.is_dir() {
            out.extend(walk(&p));
        } else {
            out.push(p);
        }
    }
    out
}

fn last_user(srv: &Server, k: usize) -> String {
    let body = srv.received()[k].json();
    let msgs = body["messages"].as_array().unwrap();
    msgs.iter().rev().find(|m| m["role"] == "user").unwrap()["content"]
        .as_str()
        .unwrap()
        .to_string()
}

#[test]
fn http_happy_path_writes_the_run_and_keeps_the_key_out() {
    let srv = Server::start(vec![
        // Streamed, as asked; the next reply is plain JSON, which a streaming request also reads.
        Canned::stream(&reply(&cut_in_script(401, 399)), Duration::ZERO),
        Canned::chat("The cutter ends ahead in the victim's lane.\nACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(t.contains("LLM: test-model at http://127.0.0.1"), "{t}");
    assert!(t.contains("checker: cut_in (cutter=401 victim=399)"), "{t}");
    assert!(t.contains("round 1: ACCEPT"), "{t}");
    for f in [
        "final.rhai",
        "final.gif",
        "report.md",
        "transcript.json",
        "state.json",
        "round_0/prompt.md",
        "round_0/reply.md",
        "round_0/script.rhai",
        "round_0/feedback.md",
        "round_0/USA_US101-3_3_T-1_0.json",
        "round_0/USA_US101-3_3_T-1_costs.json",
        "round_1/reply.md",
    ] {
        assert!(dir.path().join(f).exists(), "{f} missing:\n{t}");
    }
    assert_eq!(
        std::fs::read_to_string(dir.path().join("final.rhai")).unwrap(),
        cut_in_script(401, 399)
    );
    // The first prompt has the generated reference, the summary naming the agents and the request.
    let first = srv.received()[0].json();
    let system = first["messages"][0]["content"].as_str().unwrap();
    assert!(system.contains(drivescript::cost::reference_markdown().trim()));
    let user = last_user(&srv, 0);
    assert!(
        user.contains("- vehicle 401:") && user.contains("- vehicle 399:"),
        "{user}"
    );
    assert!(user.contains(REQUEST), "{user}");
    // The refinement carries the term table with spreads, the checker and the motion at 1 Hz.
    let refine = last_user(&srv, 1);
    for want in [
        "| ends_ahead |",
        "final min",
        "checker cut_in",
        "Agent 401: t (s)",
        "  4 s: (",
    ] {
        assert!(refine.contains(want), "{want:?} missing from:\n{refine}");
    }
    let tr: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("transcript.json")).unwrap())
            .unwrap();
    assert_eq!(tr["model"], "test-model");
    let llm: Vec<&serde_json::Value> = tr["records"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["phase"] == "llm")
        .collect();
    assert_eq!(llm.len(), 2);
    // The transcript records the whole streamed reply.
    assert_eq!(llm[0]["detail"]["streamed"], true);
    assert_eq!(llm[0]["detail"]["request"]["stream"], true);
    assert_eq!(
        llm[0]["detail"]["reply"].as_str().unwrap(),
        reply(&cut_in_script(401, 399))
    );
    assert!(llm[1]["detail"].get("streamed").is_none());
    // The server read the whole prompt, and the estimate made before sending is near its count.
    let read = common::llm_server::prompt_tokens(&srv.received()[0].body);
    assert_eq!(llm[0]["detail"]["usage"]["prompt_tokens"], read);
    let estimate = llm[0]["detail"]["estimated_prompt_tokens"]
        .as_u64()
        .unwrap();
    assert!(
        estimate >= read && estimate < 2 * read,
        "{estimate} vs {read}"
    );
    assert_eq!(llm[0]["detail"]["request"]["model"], "test-model");
    assert!(tr["records"]
        .as_array()
        .unwrap()
        .iter()
        .any(|r| r["phase"] == "sample"));
    assert_no_key(dir.path());
}

#[test]
fn a_script_past_the_script_budget_goes_back_to_the_model_and_the_run_goes_on() {
    // Tens of milliseconds per evaluation: the hundreds of a sampling run take far more than
    // the 2 s budget. The model wrote it, so it is the model's to fix: it used to end the run
    // with an error (exit 1) instead of being that round's feedback.
    let slow = "let n = 0; for i in 0..200000 { n += 1; }\nlet a = agent(401);\n\
                term(\"far\", square(a.x.last() - 1000.0));\n";
    let srv = Server::start(vec![Canned::chat(&reply(slow)), Canned::chat(&reply(IDLE))]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(
        dir.path(),
        &["--script-budget", "2", "--rounds", "0"],
        Some(&srv.url),
    );
    let t = text(&out);
    // The second script was sampled, and the rounds ran out on it: not met, no error.
    assert_eq!(out.status.code(), Some(2), "{t}");
    assert!(t.contains("round 0: script over budget"), "{t}");
    let said = std::fs::read_to_string(dir.path().join("round_0/budget.txt")).unwrap();
    assert!(
        said.starts_with("your script took ")
            && said.contains(" evaluations (mean ")
            && said.contains(" ms each); the budget for script evaluation is 2 s")
            && said.contains("simplify it"),
        "{said}"
    );
    assert_eq!(srv.received().len(), 2, "{t}");
    let back = last_user(&srv, 1);
    assert!(back.contains(said.trim()), "{back}");
    assert!(!dir
        .path()
        .join("round_0/USA_US101-3_3_T-1_costs.json")
        .exists());
    assert!(dir
        .path()
        .join("round_1/USA_US101-3_3_T-1_costs.json")
        .exists());
    let tr = std::fs::read_to_string(dir.path().join("transcript.json")).unwrap();
    assert!(tr.contains("\"script over budget\""), "{tr}");
}

/// A script that validates but fails while sampled: validation runs it on the recorded
/// future, where 401 ends 29.8669 m from its start; every sample ends elsewhere, and there
/// the script indexes past an array's end (line 3).
const FAILS_IN_SAMPLING: &str =
    "let a = agent(401);\nlet d = a.x.last().value() - a.x.first().value();\n\
     if abs(d - 29.8669) > 0.01 { let v = [0.0]; d += v[3]; }\n\
     term(\"far\", square(a.x.last() - 1000.0));\n";

#[test]
fn a_script_that_fails_while_sampled_goes_back_to_the_model_and_the_run_goes_on() {
    // The model wrote it: the runtime error used to end the run (exit 1) instead of being
    // that round's feedback.
    let srv = Server::start(vec![
        Canned::chat(&reply(FAILS_IN_SAMPLING)),
        Canned::chat(&reply(IDLE)),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &["--rounds", "0"], Some(&srv.url));
    let t = text(&out);
    // The second script was sampled, and the rounds ran out on it: not met, no error.
    assert_eq!(out.status.code(), Some(2), "{t}");
    assert!(
        t.contains("round 0: script failed in sampling: script.rhai:3:"),
        "{t}"
    );
    let said = std::fs::read_to_string(dir.path().join("round_0/sampling.txt")).unwrap();
    assert!(
        said.starts_with("your script passed validation but failed while it was being sampled")
            && said.contains("script.rhai:3:")
            && said.contains("out of bounds"),
        "{said}"
    );
    assert_eq!(srv.received().len(), 2, "{t}");
    let back = last_user(&srv, 1);
    assert!(back.contains(said.trim()), "{back}");
    assert!(dir
        .path()
        .join("round_1/USA_US101-3_3_T-1_costs.json")
        .exists());
    let tr = std::fs::read_to_string(dir.path().join("transcript.json")).unwrap();
    assert!(tr.contains("\"script failed in sampling\""), "{tr}");
}

#[test]
fn the_rules_planner_taking_over_says_the_last_script_failed_while_sampled() {
    // Round 0's script is sampled, round 1's fails while sampled (round_1/sampling.txt), and
    // the server stops answering; the rules planner, resumed in its place, cannot repair that
    // script. It said "cannot repair a script that fails validation", which it had passed.
    let srv = Server::start(vec![
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat(&reply(FAILS_IN_SAMPLING)),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &["--attempts", "1"], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(t.contains("round 1: script failed in sampling"), "{t}");
    assert!(dir.path().join("round_1/sampling.txt").is_file(), "{t}");
    let out = ask(&["--resume", s(dir.path()), "--llm", "rules"], None);
    let t = text(&out);
    assert!(
        t.contains(
            "the rules planner cannot repair the model's (test-model) last script: it passed \
             validation but failed while being sampled: script.rhai:3:"
        ) && t.contains("out of bounds"),
        "{t}"
    );
    assert!(!t.contains("fails validation"), "{t}");
    assert!(!t.contains("your script"), "{t}");
}

#[test]
fn syntax_errors_and_unknown_agents_go_back_with_line_numbers_before_any_sampling() {
    let broken = "let a = agent(401);\nterm(\"x\", relu(a.x.last() - );\n";
    let unknown = cut_in_script(401, 9999);
    let srv = Server::start(vec![
        Canned::chat(&reply(broken)),
        Canned::chat(&reply(&unknown)),
        Canned::chat("Sorry, here it is fixed, no code."),
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat("ACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    let v0 = std::fs::read_to_string(dir.path().join("round_0/validation.txt")).unwrap();
    assert!(v0.contains("script.rhai:2:"), "{v0}");
    let back = last_user(&srv, 1);
    assert!(
        back.contains("nothing was sampled") && back.contains("script.rhai:2:"),
        "{back}"
    );
    let back = last_user(&srv, 2);
    assert!(back.contains("unknown agent id 9999"), "{back}");
    let back = last_user(&srv, 3);
    assert!(back.contains("no ```rhai code block"), "{back}");
    // Sampling happened once, in round 3.
    assert!(!dir
        .path()
        .join("round_0/USA_US101-3_3_T-1_costs.json")
        .exists());
    assert!(!dir
        .path()
        .join("round_1/USA_US101-3_3_T-1_costs.json")
        .exists());
    assert!(dir
        .path()
        .join("round_3/USA_US101-3_3_T-1_costs.json")
        .exists());
}

#[test]
fn a_failing_behaviour_is_repaired_and_an_accept_against_the_numbers_is_refused() {
    // A script that pulls nobody: the cut-in checker fails, so ACCEPT is answered with the
    // numbers; the repaired script passes.
    let srv = Server::start(vec![
        Canned::chat(&reply(IDLE)),
        Canned::chat("Looks fine to me.\nACCEPT"),
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat("ACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(t.contains("ACCEPT not accepted"), "{t}");
    let refused = last_user(&srv, 2);
    assert!(
        refused.contains("ACCEPT is not accepted") && refused.contains("checker cut_in"),
        "{refused}"
    );
    let report = std::fs::read_to_string(dir.path().join("report.md")).unwrap();
    assert!(report.contains("accepted: sample"), "{report}");
    assert!(report.contains("round 2"), "{report}");
}

#[test]
fn rounds_run_out_with_exit_2_and_a_final_script() {
    // The second reply reports no usage: the truncation check cannot run, and ask says so.
    let bare = serde_json::json!({
        "choices": [{"index": 0, "message": {"role": "assistant", "content": reply(IDLE)}, "finish_reason": "stop"}]
    });
    let srv = Server::start(vec![
        Canned::chat(&reply(IDLE)),
        Canned::raw(200, &bare.to_string()),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(
        dir.path(),
        &["--rounds", "1", "--no-stream"],
        Some(&srv.url),
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(2), "{t}");
    assert!(t.contains("the rounds ran out"), "{t}");
    let said: Vec<&str> = t
        .lines()
        .filter(|l| l.contains("reported no token usage, so a prompt cut to its context window"))
        .collect();
    assert!(
        said.len() == 1 && said[0].starts_with("round 1: reply in"),
        "{t}"
    );
    assert_eq!(srv.received().len(), 2);
    assert_eq!(srv.received()[0].json()["stream"], false);
    assert!(dir.path().join("final.rhai").exists());
}

#[test]
fn a_run_stopped_by_server_errors_resumes_where_it_stopped() {
    let e500 = Canned::raw(503, "Service Unavailable");
    let srv = Server::start(vec![
        Canned::chat(&reply(&cut_in_script(401, 399))),
        e500.clone(),
        e500.clone(),
        e500,
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains("HTTP 503 after 3 attempt(s): Service Unavailable"),
        "{t}"
    );
    assert!(!t.contains("panicked"), "{t}");
    // A second server answers the round that was interrupted.
    let srv2 = Server::start(vec![Canned::chat("ACCEPT")]);
    let out = ask(&["--resume", s(dir.path())], Some(&srv2.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(t.contains("round 1: ACCEPT"), "{t}");
    assert_eq!(srv2.received().len(), 1);
    // Starting over in the same directory is refused with what to do instead.
    let out = ask(
        &[s(&samples().join(SCENE)), REQUEST, "-o", s(dir.path())],
        Some(&srv2.url),
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(t.contains("--resume") && t.contains("--continue"), "{t}");
}

/// The seed and reply share a run sends are those it recorded, not the flags' defaults, when
/// it is taken up again: a resumed or continued run asks the server as the run started did.
#[test]
fn a_resumed_or_continued_run_sends_the_seed_and_reply_share_it_recorded() {
    let srv = Server::start(vec![
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::raw(503, "Service Unavailable"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(
        dir.path(),
        &[
            "--seed",
            "7",
            "--context",
            "16384",
            "--max-tokens",
            "1500",
            "--attempts",
            "1",
        ],
        Some(&srv.url),
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    let sent = |srv: &Server, k: usize| {
        let b = srv.received()[k].json();
        (b["seed"].clone(), b["max_tokens"].clone())
    };
    let recorded = (serde_json::json!(7), serde_json::json!(1500));
    assert_eq!(sent(&srv, 0), recorded);
    assert_eq!(sent(&srv, 1), recorded);
    // Neither --seed nor --max-tokens is given again: the run's own settings are sent.
    let srv2 = Server::start(vec![Canned::raw(503, "Service Unavailable")]);
    let out = ask(
        &["--resume", s(dir.path()), "--attempts", "1"],
        Some(&srv2.url),
    );
    let t = text(&out);
    assert!(t.contains("HTTP 503"), "{t}");
    assert_eq!(sent(&srv2, 0), recorded, "{t}");
    let srv3 = Server::start(vec![Canned::raw(503, "Service Unavailable")]);
    let out = ask(
        &[
            "--continue",
            s(dir.path()),
            "and then vehicle 399 brakes",
            "--attempts",
            "1",
        ],
        Some(&srv3.url),
    );
    let t = text(&out);
    assert!(t.contains("HTTP 503"), "{t}");
    assert_eq!(sent(&srv3, 0), recorded, "{t}");
    // The reply's share of the window is the run's: another --max-tokens is refused, not
    // dropped.
    let out = ask(
        &["--resume", s(dir.path()), "--max-tokens", "2000"],
        Some(&srv3.url),
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains("--max-tokens: the run fits its prompts to --context 16384 with 1500 tokens"),
        "{t}"
    );
    assert_eq!(srv3.received().len(), 1, "{t}");
}

#[test]
fn the_manual_backend_round_trips_through_files() {
    let dir = tempfile::tempdir().unwrap();
    let d = s(dir.path());
    let out = ask(
        &[
            s(&samples().join(SCENE)),
            REQUEST,
            "-o",
            d,
            "--llm",
            "manual",
        ],
        None,
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(
        t.contains("round_0/prompt.md") && t.contains("round_0/reply.md"),
        "{t}"
    );
    assert!(t.contains("--resume"), "{t}");
    let prompt = std::fs::read_to_string(dir.path().join("round_0/prompt.md")).unwrap();
    assert!(prompt.contains("# Reference (generated from the engine)") && prompt.contains(REQUEST));
    // Resuming without a reply says the same again.
    let t = text(&ask(&["--resume", d], None));
    assert!(t.contains("waiting for a reply"), "{t}");
    // A reply saved as UTF-16 is said to be unreadable, not waited for again.
    let utf16: Vec<u8> = [0xFF, 0xFE]
        .into_iter()
        .chain("ACCEPT\n".encode_utf16().flat_map(u16::to_le_bytes))
        .collect();
    std::fs::write(dir.path().join("round_0/reply.md"), utf16).unwrap();
    let out = ask(&["--resume", d], None);
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains("round_0/reply.md: cannot read the reply (not UTF-8"),
        "{t}"
    );
    std::fs::write(
        dir.path().join("round_0/reply.md"),
        reply(&cut_in_script(401, 399)),
    )
    .unwrap();
    let t = text(&ask(&["--resume", d], None));
    assert!(t.contains("round 0: sample 0"), "{t}");
    assert!(t.contains("round_1/prompt.md"), "{t}");
    let p1 = std::fs::read_to_string(dir.path().join("round_1/prompt.md")).unwrap();
    assert!(p1.contains("| ends_ahead |"), "{p1}");
    std::fs::write(dir.path().join("round_1/reply.md"), "ACCEPT\n").unwrap();
    let out = ask(&["--resume", d], None);
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(t.contains("accepted"), "{t}");
    assert!(dir.path().join("final.rhai").exists());
}

#[test]
fn a_manual_reply_is_held_to_the_size_a_server_s_is() {
    // A 4 MB file saved as the reply was taken, kept in state.json and every later round's
    // messages.json, and sent again with every later round (a server's is refused over 1 MB).
    let dir = tempfile::tempdir().unwrap();
    let d = s(dir.path());
    let scene = samples().join(SCENE);
    let args = [s(&scene), REQUEST, "-o", d, "--llm", "manual"];
    let out = ask(&args, None);
    assert_eq!(out.status.code(), Some(0), "{}", text(&out));
    let big = format!("{}\n{}", reply(IDLE), "x".repeat(4 << 20));
    std::fs::write(dir.path().join("round_0/reply.md"), big).unwrap();
    let out = ask(&["--resume", d], None);
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains("round_0/reply.md: cannot read the reply (")
            && t.contains("the most for a model's reply"),
        "{t}"
    );
    assert!(!dir.path().join("round_1").exists(), "{t}");
    // A link planted as the reply had what it named read into state.json and every later
    // prompt: refused, and nothing of the file it names is kept.
    let reply_md = dir.path().join("round_0/reply.md");
    std::fs::remove_file(&reply_md).unwrap();
    let secret = dir.path().join("secret.md");
    std::fs::write(&secret, reply(IDLE) + "SECRET-TOKEN-123\n").unwrap();
    std::os::unix::fs::symlink(&secret, &reply_md).unwrap();
    let out = ask(&["--resume", d], None);
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains("round_0/reply.md: is a symbolic link (to ") && t.contains("), not the reply"),
        "{t}"
    );
    let state = std::fs::read_to_string(dir.path().join("state.json")).unwrap();
    assert!(!state.contains("SECRET-TOKEN"), "{state}");
    assert!(!dir.path().join("round_1").exists(), "{t}");
}

#[test]
fn a_run_started_with_relative_paths_resumes_from_another_directory() {
    // state.json kept the scene and the prompts as typed; `--resume` from any other directory
    // said "the scene ... changed (or went) since the run started ...; start a new run on it".
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let out = ask(
        &[
            &format!("data/samples/{SCENE}"),
            REQUEST,
            "-o",
            s(&run),
            "--llm",
            "manual",
            "--rounds",
            "0",
            "--samples",
            "1",
        ],
        None,
    );
    assert_eq!(out.status.code(), Some(0), "{}", text(&out));
    std::fs::write(
        run.join("round_0/reply.md"),
        reply(&cut_in_script(401, 399)),
    )
    .unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
        .args(["ask", "--resume", s(&run)])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(t.contains("round 0: sample 0"), "{t}");
    // A run recorded before paths were absolute says where to run it from.
    let state = run.join("state.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&state).unwrap()).unwrap();
    v["scene"] = format!("data/samples/{SCENE}").into();
    std::fs::write(&state, v.to_string()).unwrap();
    let out = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
        .args(["ask", "--resume", s(&run)])
        .current_dir(dir.path())
        .output()
        .unwrap();
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains(&format!(
            "the scene data/samples/{SCENE} is not found from {}: the run recorded it relative",
            dir.path().display()
        )),
        "{t}"
    );
}

#[test]
fn an_empty_request_or_follow_up_is_refused_before_the_run_starts() {
    // "  " started a manual run whose prompt asked about nothing; a blank follow-up went to
    // the rules planner, which said it did not understand "".
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let scene = samples().join(SCENE);
    let out = ask(&[s(&scene), "  ", "-o", s(&run), "--llm", "manual"], None);
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(t.contains("the request is empty"), "{t}");
    assert!(!run.exists(), "{t}");
    let out = ask(
        &[s(&scene), REQUEST, "-o", s(&run), "--llm", "manual"],
        None,
    );
    assert_eq!(out.status.code(), Some(0), "{}", text(&out));
    std::fs::write(
        run.join("round_0/reply.md"),
        reply(&cut_in_script(401, 399)),
    )
    .unwrap();
    let out = ask(&["--resume", s(&run)], None);
    assert!(text(&out).contains("round 0: sample 0"), "{}", text(&out));
    let out = ask(&["--continue", s(&run), "\t"], None);
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(t.contains("the request is empty"), "{t}");
}

#[test]
fn the_rules_planner_is_the_default_without_an_llm_and_follow_ups_revise_its_run() {
    let dir = tempfile::tempdir().unwrap();
    let d = s(dir.path());
    let out = ask(
        &[
            s(&samples().join(SCENE)),
            "vehicle 401 cuts in front of vehicle 399, vehicle 405 drives off the road",
            "-o",
            d,
        ],
        None,
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(
        t.contains("none configured") && t.contains("rules planner"),
        "{t}"
    );
    assert!(t.contains("checker: off_road (vehicle=405)"), "{t}");
    let script = std::fs::read_to_string(dir.path().join("final.rhai")).unwrap();
    assert!(
        script.contains("agent(401)") && script.contains("agent(405)"),
        "{script}"
    );
    // A follow-up it understands adds an event and samples again.
    let out = ask(&["--continue", d, "vehicle 399 keeps below 40 km/h"], None);
    let t = text(&out);
    assert!(
        out.status.code() == Some(0) || out.status.code() == Some(2),
        "{t}"
    );
    assert!(t.contains("follow-up"), "{t}");
    let script = std::fs::read_to_string(dir.path().join("final.rhai")).unwrap();
    assert!(script.contains("speed_limit"), "{script}");
    // One it does not understand says an LLM is needed.
    let out = ask(&["--continue", d, "make the cut-in more abrupt"], None);
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(t.contains("DRIVESCRIPT_LLM_URL"), "{t}");
    // As does a first request it does not know.
    let dir2 = tempfile::tempdir().unwrap();
    let out = ask(
        &[
            s(&samples().join(SCENE)),
            "a bus driver sneezes",
            "-o",
            s(dir2.path()),
        ],
        None,
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains("does not understand") && t.contains("--llm manual"),
        "{t}"
    );
}

/// `ask` guides with the strength chosen for its checkpoint (config.json's `guidance_lambda`),
/// as `simulate` does, and keeps it in state.json, so that `--resume` samples as it began.
#[test]
fn ask_guides_with_the_strength_chosen_for_its_checkpoint() {
    let dir = tempfile::tempdir().unwrap();
    let ck = common::checkpoint_copy(dir.path());
    let mut cfg: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(ck.join("config.json")).unwrap()).unwrap();
    cfg["guidance_lambda"] = serde_json::json!(5.5);
    std::fs::write(ck.join("config.json"), cfg.to_string()).unwrap();
    for (checkpoint, want) in [(Path::new("data/checkpoint"), 3.0), (ck.as_path(), 5.5)] {
        let run = dir.path().join(format!("run{want}"));
        let scene = samples().join(SCENE);
        let out = ask(
            &[
                s(&scene),
                "vehicle 405 drives off the road",
                "-o",
                s(&run),
                "--checkpoint",
                s(checkpoint),
                "--samples",
                "1",
                "--rounds",
                "0",
            ],
            None,
        );
        let t = text(&out);
        assert!(matches!(out.status.code(), Some(0 | 2)), "{t}");
        let state: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(run.join("state.json")).unwrap())
                .unwrap();
        assert_eq!(state["config"]["lambda"], want, "{}", checkpoint.display());
    }
}

#[test]
fn prompt_show_prints_the_first_prompt() {
    let out = common::ok(&[
        "prompt",
        "show",
        s(&samples().join(SCENE)),
        REQUEST,
        "--no-frenet",
    ]);
    assert!(
        out.contains("<!-- system -->") && out.contains("<!-- user -->"),
        "{out}"
    );
    assert!(out.contains("- vehicle 401:") && out.contains(REQUEST));
    assert!(!out.contains("## Frenet frame"));
    let out = common::ok(&["prompt", "show", s(&samples().join(SCENE)), REQUEST]);
    assert!(out.contains(drivescript::cost::reference_markdown().trim()));
    // As `ask` refuses it: a prompt asking for nothing is not one to show.
    for empty in ["", "  \n"] {
        let err = common::fails(&["prompt", "show", s(&samples().join(SCENE)), empty]);
        assert!(err.contains("the request is empty"), "{err}");
    }
}

#[test]
fn a_batch_runs_every_pair_and_writes_a_summary_and_rollouts_eval_reads() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join(SCENE);
    let file = dir.path().join("requests.yaml");
    std::fs::write(
        &file,
        format!(
            "scenes: {}\nentries:\n  - request: \"vehicle 401 cuts in front of vehicle 399\"\n    behaviour: cut_in\n    params: {{cutter: 401, victim: 399}}\n  - request: \"vehicle {{vehicle}} drives off the road\"\n    behaviour: off_road\n",
            scene.display()
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    let o = ask(&["--batch", s(&file), "-o", s(&out), "--rounds", "1"], None);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(0), "{t}");
    assert!(t.contains("2 pairs") && t.contains("[2/2]"), "{t}");
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(
        summary.contains("| cut_in | 1 |") && summary.contains("| off_road | 1 |"),
        "{summary}"
    );
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    assert_eq!(json["instances"].as_array().unwrap().len(), 2);
    let rollouts = out.join("rollouts/cut_in");
    assert!(rollouts.join("USA_US101-3_3_T-1_3.json").exists());
    assert!(rollouts.join("unguided/USA_US101-3_3_T-1_3.json").exists());
    // `eval` scores those rollouts with the same checker, against the same unguided twins.
    let e = common::ok(&[
        "eval",
        s(&scene),
        "--task",
        "behaviour",
        "--behaviour",
        "cut_in",
        "--param",
        "cutter=401",
        "victim=399",
        "--rollouts",
        s(&rollouts),
        "--unguided",
        s(&rollouts.join("unguided")),
        "--samples",
        "4",
    ]);
    assert!(e.contains("cut_in"), "{e}");
    // A bad entry names its line.
    std::fs::write(
        &file,
        "entries:\n  - request: x\n    behaviour: flying\n    scene: a.xml\n",
    )
    .unwrap();
    let o = ask(&["--batch", s(&file), "-o", s(&out)], None);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("entry 1 (line 2)") && t.contains("flying"),
        "{t}"
    );
}

#[test]
fn a_run_killed_after_the_reply_resumes_without_asking_again() {
    // The only reply is the round-0 script; the run is killed as soon as it is on disk
    // (while sampling, most likely), and --resume must go on from that reply.
    let srv = Server::start(vec![Canned::chat(&reply(&cut_in_script(401, 399)))]);
    let dir = tempfile::tempdir().unwrap();
    let mut child = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
        .args([
            "ask",
            s(&samples().join(SCENE)),
            REQUEST,
            "-o",
            s(dir.path()),
        ])
        .args(["--backoff", "0.02"])
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("DRIVESCRIPT_LLM_URL", &srv.url)
        .env("DRIVESCRIPT_LLM_MODEL", "test-model")
        .env("DRIVESCRIPT_LLM_KEY", "sk-test-secret")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .unwrap();
    let reply_md = dir.path().join("round_0/reply.md");
    let t0 = std::time::Instant::now();
    while !reply_md.exists() {
        assert!(t0.elapsed().as_secs() < 120, "no reply.md after 2 minutes");
        std::thread::sleep(std::time::Duration::from_millis(5));
    }
    child.kill().unwrap();
    child.wait().unwrap();
    assert_eq!(srv.received().len(), 1);
    let srv2 = Server::start(vec![Canned::chat("ACCEPT")]);
    let out = ask(&["--resume", s(dir.path())], Some(&srv2.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(t.contains("round 1: ACCEPT"), "{t}");
    // Round 0 was not asked again: the second server answered round 1 only.
    let got = srv2.received();
    assert_eq!(got.len(), 1, "{t}");
    assert!(
        got[0].body.contains("```rhai"),
        "round 1 carries round 0's script"
    );
    let transcript = std::fs::read_to_string(dir.path().join("transcript.json")).unwrap();
    assert!(transcript.contains("\"llm\""), "{transcript}");
    assert_no_key(dir.path());
}

#[test]
fn a_batch_stopped_by_an_error_continues_when_run_again() {
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join(SCENE);
    let file = dir.path().join("requests.yaml");
    let write = |first: &str| {
        std::fs::write(
            &file,
            format!(
                "scenes: {}\nentries:\n  - request: \"{first}\"\n    behaviour: cut_in\n    params: {{cutter: 401, victim: 399}}\n  - request: \"vehicle 405 drives off the road\"\n    behaviour: off_road\n    params: {{vehicle: 405}}\n",
                scene.display()
            ),
        )
        .unwrap()
    };
    write("vehicle 401 cuts in front of vehicle 399");
    let out = dir.path().join("out");
    let e503 = Canned::raw(503, "Service Unavailable");
    let srv = Server::start(vec![
        Canned::chat(&reply(&cut_in_script(401, 399))),
        e503.clone(),
        e503.clone(),
        e503,
    ]);
    let args = ["--batch", s(&file), "-o", s(&out), "--rounds", "0"];
    let o = ask(&args, Some(&srv.url));
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("pair 2 of 2") && t.contains("run the same command again"),
        "{t}"
    );
    assert!(t.contains("HTTP 503"), "{t}");
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(summary.contains("1 of 2 pairs done"), "{summary}");
    // Run again: the finished pair is read back, not asked again; the stopped one runs.
    // (Another behaviour: a second cut-in of the scene would replace the first's rollouts.)
    let srv2 = Server::start(vec![Canned::chat(&reply(
        "let a = agent(405);\nterm(\"off\", relu(a.edge_distance.last() + 1.0), 1.0);\n",
    ))]);
    let o = ask(&args, Some(&srv2.url));
    let t = text(&o);
    assert_eq!(o.status.code(), Some(0), "{t}");
    assert!(t.contains("[1/2]") && t.contains("(continued run)"), "{t}");
    assert_eq!(srv2.received().len(), 1, "{t}");
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(summary.contains("2 of 2 pairs done"), "{summary}");
    // A batch file whose pair changed does not reuse the old run.
    write("vehicle 401 cuts in front of vehicle 399 abruptly");
    let o = ask(&args, Some(&srv2.url));
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("holds a run of the request"), "{t}");
    // In the request's words, not Rust's `Some("...")`.
    assert!(
        t.contains("the request \"vehicle 401 cuts in front of vehicle 399\"")
            && !t.contains("Some("),
        "{t}"
    );
    // Run again with another setting: the pairs done before were reported with their own
    // settings beside new ones, as one batch, exit 0.
    write("vehicle 401 cuts in front of vehicle 399");
    for (flag, value, says) in [
        (
            "--seed",
            "5",
            "made with seed = 1, and this batch runs with seed = 5",
        ),
        (
            "--samples",
            "2",
            "made with samples = 4, and this batch runs with samples = 2",
        ),
        (
            "--rounds",
            "2",
            "made with rounds = 0, and this batch runs with rounds = 2",
        ),
    ] {
        let mut again = args.to_vec();
        if flag == "--rounds" {
            again.truncate(again.len() - 2);
        }
        again.extend([flag, value]);
        let o = ask(&again, Some(&srv2.url));
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(
            t.contains(says) && t.contains("the settings it started with"),
            "{t}"
        );
        // Running the same command again meets the same refusal: not advised.
        assert!(
            t.contains("cannot be continued") && !t.contains("run the same command again"),
            "{t}"
        );
    }
    assert_eq!(srv2.received().len(), 1);
}

#[test]
fn batch_shards_share_one_directory_and_a_plain_run_summarises_them() {
    let dir = tempfile::tempdir().unwrap();
    let scenes = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes");
    let file = dir.path().join("requests.yaml");
    std::fs::write(
        &file,
        format!(
            "scenes: {}\nentries:\n  - request: \"vehicle {{vehicle}} drives off the road\"\n    behaviour: off_road\n",
            scenes.display()
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    let run = |extra: &[&str]| {
        let mut a = vec![
            "--batch",
            s(&file),
            "-o",
            s(&out),
            "--rounds",
            "0",
            "--samples",
            "1",
        ];
        a.extend_from_slice(extra);
        let o = ask(&a, None);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(0), "{t}");
        t
    };
    let done = |t: &str| t.lines().filter(|l| l.starts_with('[')).count();
    let (a, b) = (run(&["--shard", "0/2"]), run(&["--shard", "1/2"]));
    let all = run(&[]);
    let n = done(&all);
    assert!(n >= 2, "{all}");
    assert_eq!(
        done(&a) + done(&b),
        n,
        "each pair in exactly one shard:\n{a}\n{b}"
    );
    assert!(done(&a) > 0 && done(&b) > 0, "{a}\n{b}");
    // The plain run only read the shards' finished runs back.
    assert_eq!(all.matches("(continued run)").count(), n, "{all}");
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    assert!(
        summary.contains(&format!("{n} of {n} pairs done")),
        "{summary}"
    );
}

#[test]
fn loop_flags_are_checked_before_any_work() {
    // --rounds 10^6 or --fixes 10^5 would have paid for a million requests; --backoff 1e308
    // panicked converting to a Duration; --max-agents 0 sent a summary of no agents.
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join(SCENE);
    for (flag, value, want) in [
        ("--rounds", "1000000", "1000000 is not in 0..=20"),
        ("--fixes", "100000", "100000 is not in 0..=20"),
        ("--samples", "0", "0 is not in 1..=1024"),
        ("--max-agents", "0", "0 is not in 1..=1000"),
        ("--attempts", "0", "0 is not in 1..=20"),
        ("--max-tokens", "0", "0 is not in 1..=1000000"),
        (
            "--backoff",
            "1e308",
            "--backoff 1e308: must be 0 to 600 seconds",
        ),
        ("--temperature", "3", "--temperature 3: must be 0 to 2"),
        ("--temperature", "NaN", "--temperature NaN: must be 0 to 2"),
        (
            "--llm-timeout",
            "-1",
            "--llm-timeout -1: must be more than 0",
        ),
        (
            "--reply-deadline",
            "0",
            "--reply-deadline 0: must be more than 0 and at most 86400 seconds",
        ),
        (
            "--tolerance",
            "-1",
            "--tolerance -1: must be finite and not negative",
        ),
    ] {
        let out = dir.path().join("run");
        let arg = format!("{flag}={value}");
        let run = ask(
            &[s(&scene), REQUEST, "-o", s(&out), "--llm", "rules", &arg],
            None,
        );
        let err = String::from_utf8_lossy(&run.stderr);
        assert!(
            matches!(run.status.code(), Some(1) | Some(2)) && err.contains(want),
            "{arg}: {err}"
        );
        assert!(!err.contains("panicked"), "{arg}: {err}");
        assert!(!out.exists(), "{arg}: wrote {}", out.display());
    }
}

/// `ask` started in the background (its output discarded), for a run that is still going.
fn ask_spawn(args: &[&str], url: &str) -> std::process::Child {
    std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"))
        .arg("ask")
        .args(args)
        .current_dir(env!("CARGO_MANIFEST_DIR"))
        .env("DRIVESCRIPT_LLM_KEY", "sk-test-secret")
        .env("DRIVESCRIPT_LLM_URL", url)
        .env("DRIVESCRIPT_LLM_MODEL", "test-model")
        .stdout(std::process::Stdio::null())
        .stderr(std::process::Stdio::null())
        .spawn()
        .expect("the binary runs")
}

/// Waits (at most a minute) until `p` exists.
fn wait_for(p: &Path) {
    let t0 = Instant::now();
    while !p.exists() {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "{} never appeared",
            p.display()
        );
        std::thread::sleep(Duration::from_millis(50));
    }
}

#[test]
fn a_run_still_going_is_locked_against_resume_continue_and_a_second_batch() {
    // The first request is answered only after a while: the run is still going meanwhile.
    let srv = Server::start(vec![Canned::chat("ACCEPT").after(Duration::from_secs(20))]);
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let mut first = ask_spawn(
        &[s(&samples().join(SCENE)), REQUEST, "-o", s(&run)],
        &srv.url,
    );
    wait_for(&run.join("round_0/prompt.md"));
    for args in [
        vec!["--resume", s(&run)],
        vec!["--continue", s(&run), "make it more abrupt"],
    ] {
        let out = ask(&args, Some(&srv.url));
        let t = text(&out);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {t}");
        assert!(
            t.contains("another drivescript process is running in it"),
            "{args:?}: {t}"
        );
    }
    let _ = first.kill();
    let _ = first.wait();
    // Two identical batches into one -o.
    let file = dir.path().join("requests.yaml");
    std::fs::write(
        &file,
        format!(
            "scenes: {}\nentries:\n  - request: \"vehicle 401 cuts in front of vehicle 399\"\n    behaviour: cut_in\n    params: {{cutter: 401, victim: 399}}\n",
            samples().join(SCENE).display()
        ),
    )
    .unwrap();
    let srv = Server::start(vec![Canned::chat("ACCEPT").after(Duration::from_secs(20))]);
    let out = dir.path().join("batch");
    let batch = ["--batch", s(&file), "-o", s(&out), "--llm", "http"];
    let mut first = ask_spawn(&batch, &srv.url);
    let t0 = Instant::now();
    while srv.received().is_empty() {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "the batch never asked"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = ask(&batch, Some(&srv.url));
    let t = text(&o);
    let _ = first.kill();
    let _ = first.wait();
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("another drivescript process is running in it"),
        "{t}"
    );
}

/// A batch file of one pair, the cut-in of [`REQUEST`] on [`SCENE`], written in `dir`.
fn one_pair_batch(dir: &Path) -> std::path::PathBuf {
    let file = dir.join("requests.yaml");
    std::fs::write(
        &file,
        format!(
            "scenes: {}\nentries:\n  - request: \"{REQUEST}\"\n    behaviour: cut_in\n    params: {{cutter: 401, victim: 399}}\n",
            samples().join(SCENE).display()
        ),
    )
    .unwrap();
    file
}

#[test]
fn a_directory_holds_one_kind_of_run_and_a_live_one_locks_out_the_other_kind() {
    let dir = tempfile::tempdir().unwrap();
    let file = one_pair_batch(dir.path());
    let scene = samples().join(SCENE);
    // Finished runs of each kind: the other kind is refused, saying what is there.
    let b = dir.path().join("batch");
    let o = ask(
        &[
            "--batch",
            s(&file),
            "-o",
            s(&b),
            "--llm",
            "rules",
            "--rounds",
            "0",
        ],
        None,
    );
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    let o = ask(&[s(&scene), REQUEST, "-o", s(&b), "--llm", "manual"], None);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("it holds an `ask --batch` run"), "{t}");
    assert!(!b.join("state.json").exists(), "{t}");
    let o = ask(&["--resume", s(&b)], None);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("it holds an `ask --batch` run") && t.contains("--resume DIR/runs/"),
        "{t}"
    );
    let r = dir.path().join("run");
    let o = ask(&[s(&scene), REQUEST, "-o", s(&r), "--llm", "manual"], None);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    let o = ask(&["--batch", s(&file), "-o", s(&r), "--llm", "rules"], None);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("it holds a single `ask` run (state.json)"),
        "{t}"
    );
    assert!(
        !r.join("summary.md").exists() && !r.join("runs").exists(),
        "{t}"
    );
    // A counter of state.json at its largest once wrapped to 0 on the next reply.
    let state = r.join("state.json");
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(&state).unwrap()).unwrap();
    v["exchange"] = serde_json::json!(u64::MAX);
    std::fs::write(&state, v.to_string()).unwrap();
    let o = ask(&["--resume", s(&r)], None);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("state.json: `exchange` is 18446744073709551615"),
        "{t}"
    );

    // A single run still going: a batch and a demo there are refused, its files kept.
    let srv = Server::start(vec![Canned::chat("ACCEPT").after(Duration::from_secs(20))]);
    let live = dir.path().join("live");
    let mut first = ask_spawn(&[s(&scene), REQUEST, "-o", s(&live)], &srv.url);
    wait_for(&live.join("round_0/prompt.md"));
    let o = ask(
        &["--batch", s(&file), "-o", s(&live), "--llm", "rules"],
        None,
    );
    let batch_text = text(&o);
    let demo = common::drivescript(&["demo", "-o", s(&live)]);
    let demo_text = text(&demo);
    let kept = live.join("state.json").exists() && live.join("round_0/prompt.md").exists();
    let _ = first.kill();
    let _ = first.wait();
    assert_eq!(o.status.code(), Some(1), "{batch_text}");
    assert!(
        batch_text.contains("it holds a single `ask` run")
            || batch_text.contains("another drivescript process is running in it"),
        "{batch_text}"
    );
    assert!(!live.join("summary.md").exists(), "{batch_text}");
    assert_eq!(demo.status.code(), Some(1), "{demo_text}");
    assert!(
        demo_text.contains("another drivescript process is running in it"),
        "{demo_text}"
    );
    assert!(kept, "{demo_text}");

    // A batch still going: a single run there is refused.
    let srv = Server::start(vec![Canned::chat("ACCEPT").after(Duration::from_secs(20))]);
    let lb = dir.path().join("live-batch");
    let mut first = ask_spawn(
        &["--batch", s(&file), "-o", s(&lb), "--llm", "http"],
        &srv.url,
    );
    let t0 = Instant::now();
    while srv.received().is_empty() {
        assert!(
            t0.elapsed() < Duration::from_secs(60),
            "the batch never asked"
        );
        std::thread::sleep(Duration::from_millis(50));
    }
    let o = ask(&[s(&scene), REQUEST, "-o", s(&lb), "--llm", "rules"], None);
    let t = text(&o);
    let _ = first.kill();
    let _ = first.wait();
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("another drivescript process is running in it (an `ask --batch`)"),
        "{t}"
    );
    assert!(!lb.join("state.json").exists(), "{t}");
}

#[test]
fn ask_keeps_the_user_s_files_and_writes_nothing_through_a_planted_round_link() {
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    std::fs::create_dir(&run).unwrap();
    std::fs::write(run.join("report.md"), "my own report").unwrap();
    let o = ask(
        &[
            s(&samples().join(SCENE)),
            REQUEST,
            "-o",
            s(&run),
            "--llm",
            "rules",
        ],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("report.md") && t.contains("will not replace it"),
        "{t}"
    );
    assert_eq!(
        std::fs::read_to_string(run.join("report.md")).unwrap(),
        "my own report"
    );
    std::fs::remove_file(run.join("report.md")).unwrap();
    // A round_0 link to a directory outside -o.
    #[cfg(unix)]
    {
        let outside = dir.path().join("outside");
        std::fs::create_dir(&outside).unwrap();
        std::os::unix::fs::symlink(&outside, run.join("round_0")).unwrap();
        let o = ask(
            &[
                s(&samples().join(SCENE)),
                REQUEST,
                "-o",
                s(&run),
                "--llm",
                "rules",
            ],
            None,
        );
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(t.contains("round_0"), "{t}");
        assert_eq!(std::fs::read_dir(&outside).unwrap().count(), 0, "{t}");
    }
}

#[test]
fn errors_about_an_entry_inside_a_run_directory_name_that_entry() {
    // They said "run directory DIR: round_0 is not a directory", naming the directory that
    // holds what is wrong, and called round_0 itself a run directory for a link inside it.
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let o = ask(
        &[
            s(&samples().join(SCENE)),
            REQUEST,
            "-o",
            s(&run),
            "--llm",
            "manual",
        ],
        None,
    );
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    let resume = || {
        let o = ask(&["--resume", s(&run)], None);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(!t.contains("run directory"), "{t}");
        t
    };
    // A file where the round's directory was.
    let r0 = run.join("round_0");
    std::fs::remove_dir_all(&r0).unwrap();
    std::fs::write(&r0, "not a round").unwrap();
    let t = resume();
    assert!(
        t.contains(&format!(
            "{}: not a directory: the run writes its files",
            r0.display()
        )),
        "{t}"
    );
    // The round's unguided/ a link out of the run.
    #[cfg(unix)]
    {
        std::fs::remove_file(&r0).unwrap();
        std::fs::create_dir(&r0).unwrap();
        let outside = dir.path().join("outside");
        std::fs::create_dir(&outside).unwrap();
        let link = r0.join("unguided");
        std::os::unix::fs::symlink(&outside, &link).unwrap();
        let t = resume();
        assert!(
            t.contains(&format!(
                "{}: a symbolic link (to {})",
                link.display(),
                outside.display()
            )),
            "{t}"
        );
        std::fs::remove_file(&link).unwrap();
    }
    // A reply saved as a link that leads nowhere ("run directory DIR: ...: No such file or
    // directory" of a name `ls` lists); a link is no reply wherever it leads.
    #[cfg(unix)]
    {
        let reply = r0.join("reply.md");
        std::os::unix::fs::symlink(dir.path().join("gone.md"), &reply).unwrap();
        let t = resume();
        assert!(
            t.contains(&format!(
                "{}: is a symbolic link (to {}), not the reply",
                reply.display(),
                dir.path().join("gone.md").display()
            )),
            "{t}"
        );
        std::fs::remove_file(&reply).unwrap();
    }
    // A damaged state.json, and one that cannot be read as a file.
    let state = run.join("state.json");
    std::fs::write(&state, "{").unwrap();
    let t = resume();
    assert!(
        t.contains(&format!("{}: the file is damaged", state.display())),
        "{t}"
    );
    std::fs::remove_file(&state).unwrap();
    std::fs::create_dir(&state).unwrap();
    let t = resume();
    assert!(
        t.contains(&format!("{}: cannot read it", state.display()))
            && t.contains("a run keeps its state there"),
        "{t}"
    );
}

#[test]
fn a_server_echoing_the_key_gets_it_into_no_output_and_no_file() {
    // In an error body: quoted in the error on stderr.
    let srv = Server::start(vec![Canned::raw(
        400,
        r#"{"error": {"message": "bad request; you sent Authorization: Bearer sk-test-secret"}}"#,
    )]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(!t.contains("sk-test-secret"), "{t}");
    assert!(t.contains("Bearer [redacted]"), "{t}");
    assert_no_key(dir.path());
    // Quoted in completions, plainly and behind JSON escapes.
    let escaped = serde_json::json!({
        "choices": [{"index": 0, "message": {"role": "assistant", "content": "The cutter ends ahead (key: \u{1}KEY).\nACCEPT"}, "finish_reason": "stop"}],
    })
    .to_string()
    .replace("\\u0001KEY", "\\u0073k-test-secret");
    let srv = Server::start(vec![
        Canned::chat(&format!(
            "{}\nI was called with Bearer sk-test-secret.\n",
            reply(&cut_in_script(401, 399))
        )),
        Canned::raw(200, &escaped),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&srv.url));
    let t = text(&out);
    assert!(!t.contains("sk-test-secret"), "{t}");
    assert!(srv.received().len() >= 2, "{t}");
    assert_no_key(dir.path());
    let reply0 = std::fs::read_to_string(dir.path().join("round_0/reply.md")).unwrap();
    assert!(reply0.contains("Bearer [redacted]"), "{reply0}");
}

#[test]
fn token_counts_from_a_hostile_server_saturate_instead_of_wrapping() {
    let huge = |content: &str| {
        let body = serde_json::json!({
            "choices": [{"index": 0, "message": {"role": "assistant", "content": content}, "finish_reason": "stop"}],
            "usage": {"prompt_tokens": u64::MAX, "completion_tokens": 10}
        });
        Canned::raw(200, &body.to_string())
    };
    let srv = Server::start(vec![
        huge(&reply(&cut_in_script(401, 399))),
        huge("The cutter ends ahead in the victim's lane.\nACCEPT"),
        huge("ACCEPT"),
        huge("ACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("requests.yaml");
    std::fs::write(
        &file,
        format!(
            "scenes: {}\nentries:\n  - request: \"vehicle 401 cuts in front of vehicle 399\"\n    behaviour: cut_in\n    params: {{cutter: 401, victim: 399}}\n",
            samples().join(SCENE).display()
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    let o = ask(
        &[
            "--batch",
            s(&file),
            "-o",
            s(&out),
            "--llm",
            "http",
            "--rounds",
            "1",
        ],
        Some(&srv.url),
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(0), "{t}");
    let json: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("summary.json")).unwrap()).unwrap();
    let tokens = json["instances"][0]["tokens"].as_u64().unwrap();
    assert_eq!(tokens, u64::MAX, "{json}");
}

#[test]
fn resume_refuses_a_scene_that_changed_since_the_run_started() {
    let dir = tempfile::tempdir().unwrap();
    let scene = dir.path().join("scene.xml");
    std::fs::copy(samples().join(SCENE), &scene).unwrap();
    let run = dir.path().join("run");
    let o = ask(
        &[s(&scene), REQUEST, "-o", s(&run), "--llm", "manual"],
        None,
    );
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    let xml = std::fs::read_to_string(&scene).unwrap();
    std::fs::write(
        &scene,
        xml.replacen("<x>-44.8542</x>", "<x>-44.8543</x>", 1),
    )
    .unwrap();
    let o = ask(&["--resume", s(&run)], None);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("scene.xml changed"), "{t}");
}

#[test]
fn resume_refuses_another_checkpoint_than_the_run_s() {
    // The run's checkpoint was not recorded: `--resume` went on with the default one (or any
    // --checkpoint given), its later rounds sampled by another model, without a word.
    let dir = tempfile::tempdir().unwrap();
    let shipped = Path::new(env!("CARGO_MANIFEST_DIR")).join("data/checkpoint");
    let own = dir.path().join("own checkpoint");
    std::fs::create_dir(&own).unwrap();
    std::fs::copy(
        shipped.join("model.safetensors"),
        own.join("model.safetensors"),
    )
    .unwrap();
    // The same network, trained further in this story: another config.json.
    let config = std::fs::read_to_string(shipped.join("config.json")).unwrap();
    std::fs::write(own.join("config.json"), format!("{config}\n")).unwrap();
    let run = dir.path().join("run");
    let o = ask(
        &[
            s(&samples().join(SCENE)),
            REQUEST,
            "-o",
            s(&run),
            "--llm",
            "manual",
            "--checkpoint",
            s(&own),
        ],
        None,
    );
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    let o = ask(&["--resume", s(&run)], None);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains(&format!(
            "the run samples with the checkpoint {} (checksum",
            own.display()
        )) && t.contains(&format!("give --checkpoint {}", own.display())),
        "{t}"
    );
    // With its own checkpoint it goes on (the manual backend waits for the reply again).
    let o = ask(&["--resume", s(&run), "--checkpoint", s(&own)], None);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
}

#[test]
fn a_reply_cut_off_at_the_token_limit_says_to_raise_max_tokens() {
    let body = serde_json::json!({
        "choices": [{"index": 0, "message": {"role": "assistant", "content": "1. Events: one cut-in.\n\n```rhai\nlet a = agent(401);\nterm(\"x\", a.x"}, "finish_reason": "length"}],
    });
    let srv = Server::start(vec![Canned::raw(200, &body.to_string())]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask(
        &[
            s(&samples().join(SCENE)),
            REQUEST,
            "-o",
            s(dir.path()),
            "--fixes",
            "0",
            "--max-tokens",
            "20",
        ],
        Some(&srv.url),
    );
    let t = text(&out);
    assert!(
        t.contains("cut off at the token limit (--max-tokens 20)")
            && t.contains("never closed")
            && t.contains("raise --max-tokens"),
        "{t}"
    );
}

#[test]
fn errors_about_files_that_are_not_run_directories_do_not_call_them_so() {
    let dir = tempfile::tempdir().unwrap();
    let missing = dir.path().join("requests.yaml");
    let out = dir.path().join("out");
    let o = ask(
        &["--batch", s(&missing), "-o", s(&out), "--llm", "rules"],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains(&format!(
            "{}: cannot read the batch file",
            missing.display()
        )) && !t.contains("run directory"),
        "{t}"
    );
    let o = ask(
        &[s(&dir.path().join("nope.xml")), REQUEST, "-o", s(&out)],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(!t.contains("run directory"), "{t}");
    // A scene file where a run directory is expected: said to be a file, not called a run
    // directory.
    let scene = dir.path().join("scene.xml");
    std::fs::copy(samples().join(SCENE), &scene).unwrap();
    let called_a_run_directory = format!("run directory {}", scene.display());
    let o = ask(
        &[s(&scene), REQUEST, "-o", s(&scene), "--llm", "rules"],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains(&format!(
            "{}: is a file, not a directory: -o names the run directory",
            scene.display()
        )) && !t.contains(&called_a_run_directory),
        "{t}"
    );
    for flag in ["--resume", "--continue"] {
        let mut args = vec![flag, s(&scene)];
        if flag == "--continue" {
            args.push("make it more abrupt");
        }
        let o = ask(&args, None);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{flag}: {t}");
        assert!(
            t.contains(&format!(
                "{}: is a file, not a run directory",
                scene.display()
            )) && !t.contains(&called_a_run_directory),
            "{flag}: {t}"
        );
    }
    // A directory without a run, and none at all.
    let empty = dir.path().join("empty");
    std::fs::create_dir(&empty).unwrap();
    for (d, says) in [
        (&empty, "holds no run to resume (there is no state.json)"),
        (&dir.path().join("missing"), "does not exist"),
    ] {
        let o = ask(&["--resume", s(d)], None);
        let t = text(&o);
        assert_eq!(o.status.code(), Some(1), "{t}");
        assert!(
            t.contains(&format!("{}: {says}", d.display())) && !t.contains("run directory /"),
            "{t}"
        );
    }
}

#[test]
fn a_batch_that_fails_before_any_result_leaves_its_directory_as_it_found_it() {
    // A failed batch left its lock files (and its first pair's empty run), which mark a
    // directory as a batch's: a single `ask` there was then refused.
    let dir = tempfile::tempdir().unwrap();
    let file = one_pair_batch(dir.path());
    let entries = |d: &Path| -> Vec<String> {
        let mut v: Vec<String> = std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .collect();
        v.sort();
        v
    };
    // No server at the first request: a new -o is not left behind ...
    let new = dir.path().join("new");
    let o = ask(&["--batch", s(&file), "-o", s(&new)], Some(&refused_url()));
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("pair 1 of 1"), "{t}");
    assert!(!new.exists(), "{:?}", entries(&new));
    // ... and an existing one keeps only what it held.
    let mine = dir.path().join("mine");
    std::fs::create_dir(&mine).unwrap();
    std::fs::write(mine.join("notes.txt"), "mine").unwrap();
    let o = ask(&["--batch", s(&file), "-o", s(&mine)], Some(&refused_url()));
    assert_eq!(o.status.code(), Some(1), "{}", text(&o));
    assert_eq!(entries(&mine), ["notes.txt"]);
    // A summary of the user's in the way, found after the batch took its locks.
    std::fs::write(mine.join("summary.md"), "my notes").unwrap();
    let o = ask(
        &["--batch", s(&file), "-o", s(&mine), "--llm", "rules"],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("summary.md: it is not a summary"), "{t}");
    // Refused before any pair: where the runs would go is not announced.
    assert!(!t.contains("runs in"), "{t}");
    assert_eq!(entries(&mine), ["notes.txt", "summary.md"]);
    // Nor for an -o that is a file.
    let o = ask(
        &[
            "--batch",
            s(&file),
            "-o",
            s(&mine.join("notes.txt")),
            "--llm",
            "rules",
        ],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(!t.contains("runs in"), "{t}");
    assert_eq!(
        std::fs::read_to_string(mine.join("notes.txt")).unwrap(),
        "mine"
    );
    // A single run there is not taken for a batch's.
    let o = ask(
        &[
            s(&samples().join(SCENE)),
            REQUEST,
            "-o",
            s(&mine),
            "--llm",
            "rules",
        ],
        None,
    );
    let t = text(&o);
    assert_ne!(o.status.code(), Some(1), "{t}");
    assert!(mine.join("state.json").exists(), "{t}");
    // A batch whose pair got a reply (paid for) before the server went: its run and marks
    // stay, to be continued by running it again.
    let e503 = Canned::raw(503, "Service Unavailable");
    let srv = Server::start(vec![
        Canned::chat(&reply(&cut_in_script(401, 399))),
        e503.clone(),
        e503.clone(),
        e503,
    ]);
    let kept = dir.path().join("kept");
    let o = ask(
        &["--batch", s(&file), "-o", s(&kept), "--rounds", "1"],
        Some(&srv.url),
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("HTTP 503"), "{t}");
    assert!(kept.join(".drivescript.batch.lock").exists(), "{t}");
    let runs = entries(&kept.join("runs"));
    assert_eq!(runs.len(), 1, "{runs:?}");
    assert!(kept
        .join("runs")
        .join(&runs[0])
        .join("round_0/reply.md")
        .exists());
}

/// `ask --batch` with the rules planner over the sample scene and these `entries:` lines,
/// which must be refused (exit 1): the temporary directory, the run's `-o` and what it printed.
fn refused_rules_batch(entries: &str) -> (tempfile::TempDir, std::path::PathBuf, String) {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("requests.yaml");
    let scenes = samples().join(SCENE).display().to_string();
    std::fs::write(&file, format!("scenes: {scenes}\nentries:\n{entries}")).unwrap();
    let out = dir.path().join("out");
    let o = ask(
        &["--batch", s(&file), "-o", s(&out), "--llm", "rules"],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    (dir, out, t)
}

#[test]
fn a_batch_pair_naming_an_agent_the_scene_lacks_is_an_error_not_a_failed_pair() {
    let (_dir, _out, t) = refused_rules_batch(
        "  - request: \"vehicle 401 cuts in front of vehicle 99999\"\n    behaviour: cut_in\n    params: {cutter: 401, victim: 99999}\n",
    );
    assert!(
        t.contains("entry on line 3") && t.contains("has no agent 99999 (cut_in victim)"),
        "{t}"
    );
}

/// Two pairs whose rollouts go to one file (`rollouts/off_road/SCENE_K.json`: one behaviour
/// asked of two agents of a scene) are refused before any run, naming both entries: the
/// second replaced the first's rollouts without a word and `eval` scored its samples for
/// both (issue 32).
#[test]
fn batch_pairs_writing_the_same_rollouts_are_refused_naming_both_entries() {
    let (_dir, out, t) = refused_rules_batch(
        "  - request: \"vehicle 401 drives off the road\"\n    behaviour: off_road\n    params: {vehicle: 401}\n  - request: \"vehicle 405 drives off the road\"\n    behaviour: off_road\n    params: {vehicle: 405}\n",
    );
    assert!(
        t.contains("entry on line 6")
            && t.contains("would replace those of the entry on line 3")
            && t.contains("rollouts/off_road/"),
        "{t}"
    );
    assert!(!out.join("rollouts").exists(), "{t}");
}

#[test]
fn an_endless_reply_body_is_an_error_not_an_abort() {
    use std::io::Write;
    let url = common::llm_server::one_shot(
        b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n",
        |stream| {
            let chunk = format!("{:x}\r\n{}\r\n", 1 << 20, " ".repeat(1 << 20));
            // Until the client hangs up.
            while stream.write_all(chunk.as_bytes()).is_ok() {}
        },
    );
    let e = ask_one(&client(&url)).unwrap_err().to_string();
    assert!(e.contains("the reply is larger than 16 MB"), "{e}");
}

#[test]
fn a_reply_that_is_not_utf8_is_an_error_not_replacement_characters() {
    // JSON is UTF-8; `"content":"\xff\xfe"` was stored as U+FFFD U+FFFD in reply.md, and the
    // user was told only that the reply had no rhai block.
    use std::io::Write;
    let streamed = common::llm_server::one_shot(
        b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nConnection: close\r\n\r\n",
        |stream| {
            let _ = stream.write_all(
                b"data: {\"choices\":[{\"index\":0,\"delta\":{\"content\":\"ok \"}}]}\n\n",
            );
            let _ = stream.write_all(
                b"data: {\"choices\":[{\"index\":0,\"delta\":{\"content\":\"\xff\xfe\"}}]}\n\n",
            );
            let _ = stream.write_all(b"data: [DONE]\n\n");
        },
    );
    let e = ask_one(&client(&streamed)).unwrap_err().to_string();
    assert!(
        e.contains("a stream event is not UTF-8 (byte 50 of the event, after 1 tokens)"),
        "{e}"
    );
    let body: &'static [u8] =
        b"{\"choices\":[{\"index\":0,\"message\":{\"role\":\"assistant\",\"content\":\"\xff\"},\"finish_reason\":\"stop\"}]}";
    let head = format!(
        "HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: {}\r\n\r\n",
        body.len()
    );
    let plain = common::llm_server::one_shot(
        Box::leak(head.into_bytes().into_boxed_slice()),
        move |stream| {
            let _ = stream.write_all(body);
        },
    );
    let e = ask_one(&client(&plain)).unwrap_err().to_string();
    assert!(
        e.contains("the reply body (HTTP 200) is not UTF-8 (byte 65)"),
        "{e}"
    );
}

#[test]
fn a_batch_scene_that_cannot_be_read_is_named_once_with_its_entry() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("requests.yaml");
    std::fs::write(
        &file,
        "scenes: nope.yaml\nentries:\n  - request: \"vehicle 1 cuts in\"\n",
    )
    .unwrap();
    let o = ask(
        &[
            "--batch",
            s(&file),
            "-o",
            s(&dir.path().join("out")),
            "--llm",
            "rules",
        ],
        None,
    );
    let t = text(&o);
    let scene = dir.path().join("nope.yaml").display().to_string();
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains(&format!(
            "requests.yaml: entry on line 3: {scene}: No such file"
        )),
        "{t}"
    );
    assert_eq!(t.matches(&scene).count(), 1, "{t}");
}

#[test]
fn a_completion_over_a_megabyte_is_refused_not_kept_and_sent_back() {
    // Within the 16 MB body cap, but no token limit gives 2 MB of text: kept, it went into
    // three files of the run directory each round and back to the server with every round.
    let big = "x".repeat(2 << 20);
    for canned in [Canned::chat(&big), Canned::stream(&big, Duration::ZERO)] {
        let srv = Server::start(vec![canned]);
        let mut cfg = HttpConfig::new(&srv.url, "test-model");
        cfg.stream = true;
        let e = HttpClient::new(cfg)
            .unwrap()
            .complete(&[Message::new("user", "x")])
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("the completion's text is 2.0 MB, over the 1 MB")
                && e.contains("--max-tokens"),
            "{e}"
        );
    }
    // At the cap it is a reply.
    let srv = Server::start(vec![Canned::chat(&"y".repeat(1 << 20))]);
    let ex = ask_one(&client(&srv.url)).unwrap();
    assert_eq!(ex.reply.len(), 1 << 20);
}

#[test]
fn a_batch_keeps_a_summary_it_did_not_write() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("requests.yaml");
    std::fs::write(
        &file,
        format!(
            "scenes: {}\nentries:\n  - request: \"vehicle 401 cuts in front of vehicle 399\"\n    behaviour: cut_in\n    params: {{cutter: 401, victim: 399}}\n",
            samples().join(SCENE).display()
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    std::fs::create_dir(&out).unwrap();
    std::fs::write(out.join("summary.md"), "my notes").unwrap();
    let o = ask(
        &["--batch", s(&file), "-o", s(&out), "--llm", "rules"],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(t.contains("summary.md: it is not a summary"), "{t}");
    assert_eq!(
        std::fs::read_to_string(out.join("summary.md")).unwrap(),
        "my notes"
    );
}

#[test]
fn a_batch_keeps_a_file_of_the_user_s_where_a_rollout_goes() {
    // A fresh -o holding rollouts/cut_in/ID_0.json (and unguided/ID_0.json) of the user's:
    // the batch replaced both with its rollouts, exit 0.
    let dir = tempfile::tempdir().unwrap();
    let file = one_pair_batch(dir.path());
    let out = dir.path().join("out");
    let mine = out.join("rollouts/cut_in/unguided/USA_US101-3_3_T-1_0.json");
    std::fs::create_dir_all(mine.parent().unwrap()).unwrap();
    std::fs::write(&mine, "my notes").unwrap();
    let o = ask(
        &[
            "--batch",
            s(&file),
            "-o",
            s(&out),
            "--llm",
            "rules",
            "--rounds",
            "0",
            "--samples",
            "1",
        ],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("unguided/USA_US101-3_3_T-1_0.json") && t.contains("is not a rollout"),
        "{t}"
    );
    assert_eq!(std::fs::read_to_string(&mine).unwrap(), "my notes");
}

#[test]
fn a_batch_refuses_a_pair_s_run_revised_with_a_follow_up() {
    // `ask --continue` on a pair's run, then the batch again: the follow-up's round was
    // counted as a refinement round of the batch's request (mean rounds 2.00 for a batch of
    // --rounds 0) and its samples copied as the pair's rollouts, exit 0.
    let dir = tempfile::tempdir().unwrap();
    let file = one_pair_batch(dir.path());
    let out = dir.path().join("out");
    let batch = || {
        ask(
            &[
                "--batch",
                s(&file),
                "-o",
                s(&out),
                "--llm",
                "rules",
                "--rounds",
                "0",
                "--samples",
                "1",
            ],
            None,
        )
    };
    let o = batch();
    assert!(o.status.success(), "{}", text(&o));
    let run = out.join("runs/000_cut_in_USA_US101-3_3_T-1");
    let o = ask(
        &["--continue", s(&run), "vehicle 401 drives off the road"],
        None,
    );
    assert!(run.join("state.json").exists(), "{}", text(&o));
    let o = batch();
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("000_cut_in_USA_US101-3_3_T-1")
            && t.contains("revised with a follow-up request")
            && t.contains("vehicle 401 drives off the road"),
        "{t}"
    );
}

#[test]
fn a_scenes_flag_naming_nothing_is_named_as_the_flag_s() {
    // It was reported as the batch file's: "requests.yaml: entry on line 3: nowhere: No such
    // file or directory (os error 2)", though the file never named that path.
    let dir = tempfile::tempdir().unwrap();
    let file = one_pair_batch(dir.path());
    let out = dir.path().join("out");
    let o = ask(
        &[
            "--batch",
            s(&file),
            "-o",
            s(&out),
            "--llm",
            "rules",
            "--scenes",
            "nowhere",
        ],
        None,
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("--scenes nowhere: no such file or directory") && !t.contains("entry on line"),
        "{t}"
    );
    assert!(!out.exists());
}

#[test]
fn a_second_batch_file_into_the_same_directory_is_refused_not_mixed_in() {
    let dir = tempfile::tempdir().unwrap();
    let first = one_pair_batch(dir.path());
    let second = dir.path().join("other.yaml");
    std::fs::write(
        &second,
        format!(
            "scenes: {}\nentries:\n  - request: \"vehicle 401 drives off the road\"\n    behaviour: off_road\n    params: {{vehicle: 401}}\n",
            samples().join(SCENE).display()
        ),
    )
    .unwrap();
    let out = dir.path().join("out");
    let run = |file: &Path| {
        ask(
            &[
                "--batch",
                s(file),
                "-o",
                s(&out),
                "--llm",
                "rules",
                "--rounds",
                "0",
            ],
            None,
        )
    };
    let o = run(&first);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
    let summary = std::fs::read_to_string(out.join("summary.md")).unwrap();
    let o = run(&second);
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains(s(&out)) && t.contains("another batch file") && t.contains("Choose another -o"),
        "{t}"
    );
    assert_eq!(
        std::fs::read_to_string(out.join("summary.md")).unwrap(),
        summary
    );
    assert_eq!(std::fs::read_dir(out.join("runs")).unwrap().count(), 1);
    // The same file again continues as before.
    let o = run(&first);
    assert_eq!(o.status.code(), Some(0), "{}", text(&o));
}

#[test]
fn a_huge_retry_after_is_capped_at_the_backoff_ceiling_and_said() {
    let srv = Server::start(vec![
        Canned::raw(429, r#"{"error": {"message": "busy"}}"#).header("Retry-After", "1000000000"),
        Canned::chat("after the capped wait"),
    ]);
    let mut cfg = HttpConfig::new(&srv.url, "m");
    cfg.backoff = Duration::from_millis(20);
    cfg.backoff_max = Duration::from_millis(300);
    let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::<String>::new()));
    let sink = seen.clone();
    let c = HttpClient::new(cfg)
        .unwrap()
        .with_observer(std::sync::Arc::new(move |e| {
            if let ClientEvent::Notice(l) = e {
                sink.lock().unwrap().push(l.to_string());
            }
        }));
    let t0 = Instant::now();
    let ex = ask_one(&c).unwrap();
    assert_eq!(ex.reply, "after the capped wait");
    assert!(
        t0.elapsed() >= Duration::from_millis(280) && t0.elapsed() < Duration::from_secs(10),
        "{:?}",
        t0.elapsed()
    );
    assert!(
        ex.retries[0].contains("not the 1e9 s Retry-After asked")
            && ex.retries[0].contains("--backoff-max 0.3 s"),
        "{:?}",
        ex.retries
    );
    let seen = seen.lock().unwrap();
    assert!(
        seen.len() == 1 && seen[0].contains("127.0.0.1") && seen[0].contains("capped"),
        "{seen:?}"
    );
}

/// A server that answers the first request with a head promising 100 kB, 1 kB of it, and then
/// a reset (`rst`) or an orderly close in the middle of the body.
fn cut_off_server(rst: bool) -> String {
    use std::io::Write;
    common::llm_server::one_shot(
        b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n",
        move |stream| {
            let _ = stream.write_all(&[b' '; 1000]);
            let _ = stream.flush();
            std::thread::sleep(Duration::from_millis(100));
            if rst {
                // SO_LINGER with a zero timeout: closing sends RST, not FIN.
                use std::os::fd::AsRawFd;
                let l = libc::linger {
                    l_onoff: 1,
                    l_linger: 0,
                };
                unsafe {
                    libc::setsockopt(
                        stream.as_raw_fd(),
                        libc::SOL_SOCKET,
                        libc::SO_LINGER,
                        &l as *const libc::linger as *const libc::c_void,
                        std::mem::size_of::<libc::linger>() as libc::socklen_t,
                    );
                }
            }
            let _ = stream.shutdown(std::net::Shutdown::Both);
        },
    )
}

#[test]
fn a_redirect_to_another_server_is_not_followed_and_says_where_it_points() {
    // Followed, a 307 sent the prompt to whatever host the server named (off the loopback
    // interface too), a 302 turned the POST into a GET without its body, and the errors named
    // only the URL the user gave ("cannot connect to ... at <the first server>").
    let elsewhere = Server::start(vec![Canned::chat("from the other server")]);
    let key = "sk-test-secret-redirect";
    let with_key = |url: &str| {
        let mut c = HttpConfig::new(url, "test-model");
        c.key = Some(key.into());
        HttpClient::new(c).unwrap()
    };
    let target = format!("{}/chat/completions", elsewhere.url);
    let srv = Server::start(vec![
        Canned::raw(307, "").header("Location", &target),
        Canned::raw(302, "").header("Location", "/v2/chat/completions"),
        Canned::raw(307, "").header("Location", &format!("http://127.0.0.1:1/x?key={key}")),
    ]);
    let c = with_key(&srv.url);
    let e = ask_one(&c).map(|x| x.reply).unwrap_err().to_string();
    assert!(
        e.contains(&format!("(HTTP 307) to {target};")) && e.contains("--llm-url"),
        "{e}"
    );
    assert!(elsewhere.received().is_empty(), "the redirect was followed");
    let e = ask_one(&c).unwrap_err().to_string();
    let port = srv.url.trim_end_matches("/v1");
    assert!(
        e.contains(&format!("(HTTP 302) to {port}/v2/chat/completions;")),
        "{e}"
    );
    let e = ask_one(&c).unwrap_err().to_string();
    assert!(
        e.contains("to http://127.0.0.1:1/x;") && !e.contains(key),
        "{e}"
    );
    assert_eq!(srv.received().len(), 3);
    // A 307 or 308 on the same server keeps the request whole and is followed.
    let moved = Server::start(vec![
        Canned::raw(308, "").header("Location", "/v1/chat/completions?moved=1"),
        Canned::chat("after the move"),
    ]);
    assert_eq!(
        ask_one(&with_key(&moved.url)).unwrap().reply,
        "after the move"
    );
    let got = moved.received();
    assert_eq!(got[1].path, "/v1/chat/completions?moved=1");
    assert_eq!(
        (got[1].method.as_str(), got[1].json()["model"].as_str()),
        ("POST", Some("test-model"))
    );
}

#[test]
fn compressed_empty_and_filtered_replies_say_what_they_are() {
    // Quoted as "not JSON; it begins \u{1f}\u{8b}..." and "EOF while parsing; it begins \"\"";
    // a filtered reply went back to the model as one without a ```rhai block.
    let filtered = serde_json::json!({
        "choices": [{"message": {"role": "assistant", "content": ""}, "finish_reason": "content_filter"}]
    });
    let srv = Server::start(vec![
        Canned::raw(200, "\u{1f}binary").header("Content-Encoding", "gzip"),
        Canned::raw(400, "\u{1f}binary").header("Content-Encoding", "br"),
        Canned::raw(204, ""),
        Canned::raw(200, &filtered.to_string()),
        Canned::events(
            vec![
                r#"{"choices":[{"delta":{"content":"1. Ev"}}]}"#.into(),
                r#"{"choices":[{"delta":{},"finish_reason":"content_filter"}]}"#.into(),
                "[DONE]".into(),
            ],
            Duration::ZERO,
        ),
    ]);
    let c = client(&srv.url);
    let e = ask_one(&c).unwrap_err().to_string();
    assert!(
        e.contains("compressed (Content-Encoding: gzip)") && !e.contains('\u{1f}'),
        "{e}"
    );
    let e = ask_one(&c).unwrap_err().to_string();
    assert!(
        e.contains("HTTP 400") && e.contains("(a body compressed as br, not read)"),
        "{e}"
    );
    let e = ask_one(&c).unwrap_err().to_string();
    assert!(e.contains("answered HTTP 204 with an empty body"), "{e}");
    for kept in ["nothing of it came", "5 characters of it came"] {
        let e = ask_one(&c).unwrap_err().to_string();
        assert!(
            e.contains("content filter stopped the reply") && e.contains(kept),
            "{e}"
        );
    }
}

#[test]
fn a_key_echoed_as_the_content_encoding_gets_into_no_message() {
    // The encoding is quoted from the header; a server putting the Authorization header it got
    // there had the key printed whole (issue 32). A key longer than the quote's 64 characters
    // must be redacted before the quote is cut.
    let key = format!("sk-{}", "k".repeat(80));
    let srv = Server::start(vec![
        Canned::raw(200, "{}").header("Content-Encoding", &format!("Bearer {key}")),
        Canned::raw(400, "{}").header("Content-Encoding", &key),
    ]);
    let mut cfg = HttpConfig::new(&srv.url, "test-model");
    cfg.key = Some(key.clone());
    cfg.attempts = 1;
    let c = HttpClient::new(cfg).unwrap();
    for _ in 0..2 {
        let e = ask_one(&c).unwrap_err().to_string();
        assert!(e.contains("[redacted]") && !e.contains("sk-kkkk"), "{e}");
    }
}

#[test]
fn a_key_echoed_where_a_message_is_cut_leaves_no_part_of_it() {
    // Quoted server text is cut (a stream event at 120 characters, an error message at 300).
    // A streamed event was cut before the key was redacted, and so was an error message whose
    // key came JSON-escaped (`\u0073k-...`, whole only once decoded): the key's head before
    // the cut was printed, "... Bearer sk-TESTKEY-a" (issue 32).
    let key = "sk-TESTKEY-abcdefghijklmnopqrstuvwxyz0123456789";
    let event = |data: String| {
        Canned::raw(200, &format!("data: {data}\n\n")).header("Content-Type", "text/event-stream")
    };
    let srv = Server::start(vec![
        event(format!("{} Bearer {key} trailing", "A".repeat(100))),
        event(
            serde_json::json!({"error": {"message": format!("{} Bearer {key}", "x".repeat(280))}})
                .to_string(),
        ),
        Canned::raw(
            400,
            &serde_json::json!({"error": {"message": format!("{} Bearer {key}", "x".repeat(280))}})
                .to_string()
                .replace("Bearer sk-", "Bearer \\u0073k-"),
        ),
    ]);
    let mut cfg = HttpConfig::new(&srv.url, "test-model");
    cfg.key = Some(key.into());
    cfg.attempts = 1;
    let c = HttpClient::new(cfg).unwrap();
    for _ in 0..3 {
        let e = ask_one(&c).unwrap_err().to_string();
        assert!(!e.contains("sk-TEST") && !e.contains("TESTKEY"), "{e}");
        assert!(e.contains("Bearer [redacted]"), "{e}");
    }
}

#[test]
fn a_key_given_as_the_url_s_user_name_gets_into_no_message() {
    // `http://KEY@host/v1` sends the key as the Basic token of "KEY:"; a server echoing it
    // (as a token or decoded) put it on the terminal.
    let srv = Server::start(vec![Canned::raw(
        400,
        r#"{"error": {"message": "bad credentials Basic c2stdXNlci1rZXktMTIzOg== (sk-user-key-123)"}}"#,
    )]);
    let url = srv.url.replace("http://", "http://sk-user-key-123@");
    let e = ask_one(&client(&url)).unwrap_err().to_string();
    assert_eq!(
        srv.received()[0].header("authorization"),
        Some("Basic c2stdXNlci1rZXktMTIzOg==")
    );
    assert!(
        e.contains("bad credentials Basic [redacted] ([redacted])"),
        "{e}"
    );
}

#[test]
fn answers_whose_head_http_cannot_read_say_what_is_wrong_with_it() {
    // Two Content-Lengths that disagree, or one that is not a number, were hyper's "invalid
    // content-length parsed", which names neither the header nor who is at fault.
    let body = r#"{"choices":[{"message":{"role":"assistant","content":"ACCEPT"}}]}"#;
    for head in [
        format!(
            "Content-Length: {}\r\nContent-Length: {}",
            body.len(),
            body.len() + 5
        ),
        "Content-Length: abc".to_string(),
    ] {
        let reply =
            format!("HTTP/1.1 200 OK\r\nContent-Type: application/json\r\n{head}\r\n\r\n{body}");
        let srv = common::llm_server::one_shot(leak(reply), |_| {});
        let e = ask_one(&client(&srv)).unwrap_err().to_string();
        assert!(
            e.contains("the answer's Content-Length header is not one whole number"),
            "{head}: {e}"
        );
    }
    let many: String = (0..200).map(|i| format!("X-Header-{i}: v\r\n")).collect();
    let reply = format!(
        "HTTP/1.1 200 OK\r\n{many}Content-Length: {}\r\n\r\n{body}",
        body.len()
    );
    let srv = common::llm_server::one_shot(leak(reply), |_| {});
    let e = ask_one(&client(&srv)).unwrap_err().to_string();
    assert!(
        e.contains("the answer's status line and headers are larger than an HTTP client reads"),
        "{e}"
    );
}

/// A reply built at run time, kept for the rest of the test process as `one_shot` needs.
fn leak(reply: String) -> &'static [u8] {
    Box::leak(reply.into_bytes().into_boxed_slice())
}

#[test]
fn tls_mismatches_and_a_connection_that_never_comes_say_what_they_are() {
    // An https:// URL for a plain-HTTP server (Ollama's own port) was "cannot connect ...
    // (connection refused or no such host): start one (`ollama serve` ...)" of a server that
    // was running; http:// for a TLS server was hyper's "invalid HTTP version parsed"; a
    // connection that never came said to raise --llm-timeout, which does not bound it.
    let plain = common::llm_server::one_shot(
        b"HTTP/1.1 400 Bad Request\r\nContent-Length: 0\r\n\r\n",
        |_| {},
    );
    let e = ask_one(&client(&plain.replace("http://", "https://")))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("the TLS (https) handshake failed (")
            && e.contains("give their URL as http://")
            && !e.contains("ollama serve"),
        "{e}"
    );
    let tls = common::llm_server::one_shot(&[0x16, 3, 1, 0, 5, 1, 2, 3, 4, 5], |_| {});
    let e = ask_one(&client(&tls)).unwrap_err().to_string();
    assert!(
        e.contains("the answer is not HTTP/1.x") && e.contains("give its URL as https://"),
        "{e}"
    );
    // Accepted by the kernel, never answered: the TLS handshake waits.
    let silent = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!("https://{}/v1", silent.local_addr().unwrap());
    let mut cfg = HttpConfig::new(&url, "m");
    cfg.connect_timeout = Duration::from_millis(300);
    let e = ask_one(&HttpClient::new(cfg).unwrap())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("no connection within 0.3 s: nothing answers at that host and port")
            && !e.contains("--llm-timeout"),
        "{e}"
    );
}

#[test]
fn a_status_line_that_is_not_http_is_named_as_such_with_the_url_once() {
    // hyper's own words, "invalid HTTP status-code parsed", with reqwest's "error sending
    // request for url (URL)" after the URL the message starts with.
    let srv = common::llm_server::one_shot(
        b"HTTP/1.1 999 \x1b[31mOops\r\nContent-Length: 2\r\n\r\n{}",
        |_| {},
    );
    let url = format!("{srv}/chat/completions");
    let e = ask_one(&client(&srv)).unwrap_err().to_string();
    assert!(
        e.contains("the answer's status line is not valid HTTP") && e.matches(&url).count() == 1,
        "{e}"
    );
}

#[cfg(unix)]
#[test]
fn a_setting_in_the_environment_that_is_not_utf8_is_an_error_not_unset() {
    // Taken for unset: a key in another encoding sent no key at all, a URL made "an LLM model
    // is set but no server URL: set DRIVESCRIPT_LLM_URL".
    use std::os::unix::ffi::OsStringExt;
    let srv = Server::start(vec![Canned::chat(&reply(&cut_in_script(401, 399)))]);
    let dir = tempfile::tempdir().unwrap();
    let garbled = std::ffi::OsString::from_vec(b"sk-\xff\xfe-secret".to_vec());
    for (name, value) in [
        ("DRIVESCRIPT_LLM_KEY", garbled.clone()),
        ("DRIVESCRIPT_LLM_URL", garbled),
    ] {
        let mut cmd = std::process::Command::new(env!("CARGO_BIN_EXE_drivescript"));
        cmd.args(["ask", s(&samples().join(SCENE)), REQUEST, "-o"])
            .arg(dir.path().join("run"))
            .args(["--rounds", "0", "--samples", "1"])
            .current_dir(env!("CARGO_MANIFEST_DIR"))
            .env("DRIVESCRIPT_LLM_URL", &srv.url)
            .env("DRIVESCRIPT_LLM_MODEL", "m")
            .env("DRIVESCRIPT_LLM_KEY", "sk-test-secret")
            .env(name, value);
        let out = cmd.output().unwrap();
        let t = text(&out);
        assert_eq!(out.status.code(), Some(1), "{name}: {t}");
        assert!(
            t.contains(&format!("{name} is set but is not UTF-8 text")) && !t.contains("secret"),
            "{t}"
        );
    }
    assert!(srv.received().is_empty());
}

#[test]
fn a_connection_reset_in_the_middle_of_the_body_is_a_reset_with_the_url_at_once() {
    for rst in [true, false] {
        let url = cut_off_server(rst);
        let t0 = Instant::now();
        let e = ask_one(&client(&url)).unwrap_err();
        // The client's silence limit is 20 s: a reset is reported when it happens.
        assert!(
            t0.elapsed() < Duration::from_secs(5),
            "{:?}: {e}",
            t0.elapsed()
        );
        assert!(matches!(e, LlmError::Reset { .. }), "{e:?}");
        let e = e.to_string();
        assert!(
            e.contains(&format!("{url}/chat/completions"))
                && e.contains("reset or closed the connection in the middle of the reply")
                && e.contains("after 1000 bytes"),
            "{e}"
        );
    }
}

#[test]
fn a_server_that_fills_usage_with_zeros_has_cut_nothing() {
    // Counted as a prompt cut to nothing: every reply refused, the user told to enlarge a
    // context window.
    let body = serde_json::json!({
        "choices": [{"index": 0, "message": {"role": "assistant", "content": "ACCEPT"}, "finish_reason": "stop"}],
        "usage": {"prompt_tokens": 0, "completion_tokens": 0, "total_tokens": 0}
    });
    let srv = Server::start(vec![Canned::raw(200, &body.to_string())]);
    let long = [Message::new("system", "rules ".repeat(4000))];
    let got = client(&srv.url).complete(&long).unwrap();
    assert_eq!(got.reply, "ACCEPT");
}

#[test]
fn a_server_that_cuts_the_prompt_to_its_window_is_an_error_naming_the_fix() {
    // Ollama's /v1 reads the last 2,048 tokens of a longer prompt and says so only in usage.
    let cut = |fingerprint: Option<&str>| {
        let mut body = serde_json::json!({
            "choices": [{"index": 0, "message": {"role": "assistant", "content": "ACCEPT"}, "finish_reason": "stop"}],
            "usage": {"prompt_tokens": 2048, "completion_tokens": 1}
        });
        if let Some(f) = fingerprint {
            body["system_fingerprint"] = f.into();
        }
        Canned::raw(200, &body.to_string())
    };
    let srv = Server::start(vec![cut(Some("fp_ollama")), cut(None)]);
    let long = [Message::new("system", "rules ".repeat(4000))];
    let e = client(&srv.url).complete(&long).unwrap_err();
    assert!(matches!(e, LlmError::ContextCut { .. }), "{e:?}");
    let e = e.to_string();
    assert!(
        e.contains("read 2048 tokens of a prompt of about 8004")
            && e.contains("OLLAMA_CONTEXT_LENGTH=16384 ollama serve")
            && e.contains("num_ctx")
            && !e.contains("--ctx-size"),
        "{e}"
    );
    // Through ask: the run stops at the first reply, before anything is sampled.
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    for want in [
        "read 2048 tokens of a prompt of about",
        "OLLAMA_CONTEXT_LENGTH",
        "--ctx-size",
        "--max-model-len",
    ] {
        assert!(t.contains(want), "{want}: {t}");
    }
    assert!(!dir.path().join("round_0/script.rhai").exists());
}

#[test]
fn a_slow_stream_is_read_as_it_comes_with_progress_and_kept_whole() {
    let text = "Plan: one cut-in. ACCEPT when it holds.";
    let srv = Server::start(vec![
        Canned::stream(text, Duration::from_millis(150)),
        Canned::chat("plain JSON to a streaming request"),
    ]);
    let mut cfg = HttpConfig::new(&srv.url, "m");
    // Less than the whole reply takes (10 events 150 ms apart), more than any gap in it.
    cfg.read_timeout = Duration::from_millis(700);
    let seen = std::sync::Arc::new(std::sync::Mutex::new(Vec::new()));
    let sink = seen.clone();
    let c = HttpClient::new(cfg)
        .unwrap()
        .with_observer(std::sync::Arc::new(move |e| match e {
            ClientEvent::Streaming { tokens, .. } => sink.lock().unwrap().push(tokens),
            ClientEvent::StreamEnd => sink.lock().unwrap().push(usize::MAX),
            ClientEvent::Notice(_) => {}
        }));
    let long = [Message::new("user", "x".repeat(3000))];
    let t0 = Instant::now();
    let ex = c.complete(&long).unwrap();
    assert!(
        t0.elapsed() > Duration::from_millis(700),
        "{:?}",
        t0.elapsed()
    );
    assert_eq!(ex.reply, text);
    assert!(ex.streamed);
    assert_eq!(ex.usage.unwrap().prompt_tokens, 750);
    let body = srv.received()[0].json();
    assert_eq!(body["stream"], true);
    assert_eq!(body["stream_options"]["include_usage"], true);
    // One event per token, counting up, then the end.
    let seen = seen.lock().unwrap().clone();
    assert_eq!(seen, vec![1, 2, 3, 4, 5, 6, 7, usize::MAX]);
    let ex = c.complete(&long).unwrap();
    assert_eq!(
        (ex.reply.as_str(), ex.streamed),
        ("plain JSON to a streaming request", false)
    );
}

#[test]
fn a_stalled_stream_is_named_as_such() {
    let tok = |w: &str| serde_json::json!({"choices": [{"delta": {"content": w}}]}).to_string();
    let srv = Server::start(vec![Canned::events(
        vec![tok("ACC"), tok("EPT"), "sleep:5000".into()],
        Duration::ZERO,
    )]);
    let mut cfg = HttpConfig::new(&srv.url, "m");
    cfg.read_timeout = Duration::from_millis(500);
    let t0 = Instant::now();
    let e = ask_one(&HttpClient::new(cfg).unwrap()).unwrap_err();
    assert!(t0.elapsed() < Duration::from_secs(3), "{:?}", t0.elapsed());
    assert!(matches!(e, LlmError::Stalled { tokens: 2, .. }), "{e:?}");
    let e = e.to_string();
    assert!(
        e.contains("the stream stalled: nothing came for 0.5 s after 2 tokens")
            && e.contains("127.0.0.1"),
        "{e}"
    );
}

/// A client with `silence` (--llm-timeout) and `deadline` (--reply-deadline), in ms.
fn client_limits(url: &str, silence: u64, deadline: u64) -> HttpClient {
    let mut cfg = HttpConfig::new(url, "m");
    cfg.backoff = Duration::from_millis(20);
    cfg.read_timeout = Duration::from_millis(silence);
    cfg.reply_deadline = Duration::from_millis(deadline);
    HttpClient::new(cfg).unwrap()
}

#[test]
fn a_stream_of_keep_alives_or_empty_chunks_without_tokens_is_a_stall() {
    // Issue 32: each arrives well within the silence limit, so the stream held ask for ever.
    let tok = serde_json::json!({"choices": [{"delta": {"content": "ACC"}}]}).to_string();
    let empty = serde_json::json!({"choices": [{"delta": {}}]}).to_string();
    for filler in [": ping".to_string(), empty] {
        let mut events = vec![tok.clone()];
        events.extend(std::iter::repeat_n(filler.clone(), 3000));
        let srv = Server::start(vec![Canned::events(events, Duration::from_millis(50))]);
        let t0 = Instant::now();
        let e = ask_one(&client_limits(&srv.url, 500, 60_000)).unwrap_err();
        assert!(
            t0.elapsed() < Duration::from_secs(3),
            "{filler}: {:?}",
            t0.elapsed()
        );
        assert!(
            matches!(
                e,
                LlmError::Stalled {
                    tokens: 1,
                    keepalive: true,
                    ..
                }
            ),
            "{filler}: {e:?}"
        );
        let e = e.to_string();
        assert!(
            e.contains(
                "no token came (only keep-alive comments or empty chunks) for 0.5 s after 1 tokens"
            ) && e.contains(&srv.url),
            "{e}"
        );
    }
}

#[test]
fn a_reply_that_never_finishes_is_abandoned_at_the_deadline() {
    use std::io::Write;
    // One token every 100 ms for ever: never silent, never without progress, never done.
    let tok = serde_json::json!({"choices": [{"delta": {"content": "x"}}]}).to_string();
    let srv = Server::start(vec![Canned::events(
        vec![tok; 3000],
        Duration::from_millis(100),
    )]);
    let t0 = Instant::now();
    let e = ask_one(&client_limits(&srv.url, 500, 1500)).unwrap_err();
    let took = t0.elapsed();
    assert!(
        took >= Duration::from_millis(1500) && took < Duration::from_secs(4),
        "{took:?}"
    );
    assert!(matches!(e, LlmError::Deadline { .. }), "{e:?}");
    let e = e.to_string();
    assert!(
        e.contains(&format!("{}/chat/completions", srv.url))
            && e.contains("abandoned the reply after 1.")
            && e.contains("past the reply deadline of 1.5 s")
            && e.contains(" tokens received")
            && e.contains("--reply-deadline"),
        "{e}"
    );
    // With --no-stream: a JSON body one byte every 50 ms.
    let url = common::llm_server::one_shot(
        b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nContent-Length: 100000\r\n\r\n",
        |stream| {
            while stream.write_all(b" ").and_then(|_| stream.flush()).is_ok() {
                std::thread::sleep(Duration::from_millis(50));
            }
        },
    );
    let t0 = Instant::now();
    let e = ask_one(&client_limits(&url, 500, 1000)).unwrap_err();
    assert!(t0.elapsed() < Duration::from_secs(3), "{:?}", t0.elapsed());
    let e = e.to_string();
    assert!(
        e.contains("past the reply deadline of 1 s") && e.contains(" bytes of the body received"),
        "{e}"
    );
    // A head that never comes is given up on at the deadline, not at the silence limit.
    let srv = Server::start(vec![Canned::chat("late").after(Duration::from_secs(20))]);
    let t0 = Instant::now();
    let e = ask_one(&client_limits(&srv.url, 20_000, 800)).unwrap_err();
    assert!(t0.elapsed() < Duration::from_secs(3), "{:?}", t0.elapsed());
    assert!(e.to_string().contains("with no reply head received"), "{e}");
}

#[test]
fn ask_abandons_a_reply_past_reply_deadline_and_says_which_flag_to_raise() {
    let tok = serde_json::json!({"choices": [{"delta": {"content": "x"}}]}).to_string();
    let srv = Server::start(vec![Canned::events(
        vec![tok; 3000],
        Duration::from_millis(100),
    )]);
    let dir = tempfile::tempdir().unwrap();
    let t0 = Instant::now();
    let out = ask_cut_in(
        dir.path(),
        &["--llm-timeout", "0.5", "--reply-deadline", "1.5"],
        Some(&srv.url),
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(t0.elapsed() < Duration::from_secs(60), "{:?}", t0.elapsed());
    assert!(
        t.contains("past the reply deadline of 1.5 s") && t.contains("--reply-deadline"),
        "{t}"
    );
    assert!(!dir.path().join("round_0/script.rhai").exists());
}

#[test]
fn retries_stop_where_the_next_wait_would_pass_the_deadline() {
    let busy =
        || Canned::raw(503, r#"{"error": {"message": "overloaded"}}"#).header("Retry-After", "1");
    let srv = Server::start(vec![busy(), busy(), busy(), busy()]);
    let mut cfg = HttpConfig::new(&srv.url, "m");
    cfg.attempts = 10;
    cfg.reply_deadline = Duration::from_millis(1500);
    let t0 = Instant::now();
    let e = ask_one(&HttpClient::new(cfg).unwrap()).unwrap_err();
    // One wait of 1 s fits; a second would end past 1.5 s.
    assert!(
        t0.elapsed() < Duration::from_millis(1500),
        "{:?}",
        t0.elapsed()
    );
    assert_eq!(srv.received().len(), 2);
    assert!(
        matches!(
            e,
            LlmError::Status {
                status: 503,
                attempts: 2,
                ..
            }
        ),
        "{e:?}"
    );
    let e = e.to_string();
    assert!(
        e.contains("overloaded; no further attempt: the wait of 1.0 s")
            && e.contains("would pass the reply deadline of 1.5 s (--reply-deadline)"),
        "{e}"
    );
}

/// The checkpoint's horizon, which the first prompt states.
fn horizon() -> usize {
    let cfg: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(
            Path::new(env!("CARGO_MANIFEST_DIR")).join("data/checkpoint/config.json"),
        )
        .unwrap(),
    )
    .unwrap();
    cfg["config"]["window"]["future"].as_u64().unwrap() as usize
}

/// The reference entries (signatures) that document any of `names`.
fn documenting(names: &std::collections::BTreeSet<String>) -> Vec<String> {
    use drivescript::llm::fit::used_names;
    let mut sigs: Vec<String> = drivescript::cost::reference()
        .iter()
        .filter(|d| used_names(d.signature).iter().any(|n| names.contains(n)))
        .map(|d| d.signature.to_string())
        .collect();
    for (_, src) in drivescript::cost::STDLIB_MODULES {
        for (sig, _) in drivescript::cost::module_functions(src) {
            if used_names(&sig).iter().any(|n| names.contains(n)) {
                sigs.push(sig);
            }
        }
    }
    sigs
}

#[test]
fn with_context_4096_every_shipped_request_fits_and_keeps_its_agents_lanes_and_functions() {
    use drivescript::llm::budget::estimate_tokens;
    use drivescript::llm::fit::{code_of, reply_budget, used_names, Window};
    use drivescript::llm::session::first_messages;
    use drivescript::llm::{Prompts, SessionConfig};
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let prompts = Prompts::load(&root.join("prompts")).unwrap();
    let window = Window {
        tokens: 4096,
        reply: reply_budget(4096, 4096),
    };
    let fitted = SessionConfig {
        context: Some(window),
        ..SessionConfig::default()
    };
    let whole = SessionConfig::default();
    let h = horizon();
    let mut checked = 0;
    for file in ["data/requests/table1.yaml", "data/requests/table3.yaml"] {
        let mut entries = drivescript::llm::batch::read_batch(&root.join(file)).unwrap();
        for e in &mut entries {
            e.scenes = vec![samples().join("commonroad"), root.join("scripts/scenes")];
        }
        let (instances, _) = drivescript::llm::batch::expand(&entries, h).unwrap();
        for e in &entries {
            assert!(
                instances
                    .iter()
                    .any(|i| i.label == e.behaviour.unwrap().name()),
                "{file}: no scene for {:?}",
                e.request
            );
        }
        for i in &instances {
            let req = [i.request.clone()];
            let m = first_messages(&prompts, &fitted, &i.scene, &req, h)
                .unwrap_or_else(|e| panic!("{}: {}: {e}", i.scene.meta.scenario_id, i.request));
            let (system, user) = (&m.messages[0].content, &m.messages[1].content);
            let tokens = estimate_tokens(&m.messages);
            assert!(
                tokens + window.reply <= 4096,
                "{}: {tokens} + {}",
                i.request,
                window.reply
            );
            assert!(!m.left_out.is_empty() && user.contains(&i.request));
            // The named agents are listed as in the whole prompt, and so are their lanes.
            let full = first_messages(&prompts, &whole, &i.scene, &req, h).unwrap();
            let not_agents = ["limit", "x", "y", "tol", "from", "within", "gap"];
            let ids = i
                .checks
                .iter()
                .flat_map(|(_, p)| p.0.iter())
                .filter(|(k, _)| !not_agents.contains(&k.as_str()))
                .filter_map(|(_, v)| v.as_f64());
            for id in ids {
                let id = id as i64;
                let line = full.messages[1]
                    .content
                    .lines()
                    .find(|l| l.starts_with("- ") && l.contains(&format!(" {id}:")))
                    .unwrap_or_else(|| panic!("agent {id} not in the whole summary"))
                    .to_string();
                assert!(
                    user.contains(&line),
                    "{}: {line} missing:\n{user}",
                    i.request
                );
                if let Some(lane) = line.split(", lane ").nth(1) {
                    let lane = lane.split(' ').next().unwrap();
                    assert!(
                        user.contains(&format!("- lane {lane}:")),
                        "{}: lane {lane} missing:\n{user}",
                        i.request
                    );
                }
            }
            // Every function the request's shipped scripts and the examples kept use.
            let mut names = std::collections::BTreeSet::new();
            for (b, _) in &i.checks {
                names.extend(used_names(drivescript::llm::rules::script_source(*b)));
            }
            for (name, text) in prompts.examples() {
                if system.contains(text.trim()) {
                    names.extend(used_names(&code_of(text)));
                } else {
                    assert!(m.left_out.iter().any(|l| l.contains(name.as_str())));
                }
            }
            for sig in documenting(&names) {
                assert!(
                    system.contains(&format!("`{sig}`")),
                    "{}: `{sig}` is not documented:\n{system}",
                    i.request
                );
            }
            checked += 1;
        }
    }
    assert!(checked >= 13, "{checked}");
}

#[test]
fn ask_with_context_sends_every_round_within_the_window_and_says_what_it_left_out() {
    use drivescript::llm::budget::estimate_tokens;
    let srv = Server::start(vec![
        Canned::chat(&reply(IDLE)),
        Canned::chat(&reply(IDLE)),
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat("ACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &["--context", "4096"], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(
        t.contains("context: fitted to --context 4096 (3072 tokens for the prompt, 1024 for the reply); left out: ")
            && t.contains("entries of the reference"),
        "{t}"
    );
    assert!(
        t.contains("round 2: fitted to --context 4096: left out 2 earlier messages"),
        "{t}"
    );
    let received = srv.received();
    assert_eq!(received.len(), 4);
    for (k, r) in received.iter().enumerate() {
        let body = r.json();
        assert_eq!(body["max_tokens"], 1024);
        let msgs: Vec<Message> = serde_json::from_value(body["messages"].clone()).unwrap();
        let tokens = estimate_tokens(&msgs);
        assert!(tokens <= 3072, "request {k}: {tokens} tokens");
        // The request is always there, and the last exchange whole.
        assert!(msgs[1].content.contains(REQUEST), "request {k}");
    }
    // The state keeps the whole conversation; only what is sent is fitted.
    let state: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(dir.path().join("state.json")).unwrap())
            .unwrap();
    assert!(state["messages"].as_array().unwrap().len() >= 8);
}

#[test]
fn a_replayed_transcript_reproduces_the_run_without_a_server() {
    let srv = Server::start(vec![
        Canned::chat(&reply(IDLE)),
        Canned::chat("Looks fine to me.\nACCEPT"),
        Canned::stream(&reply(&cut_in_script(401, 399)), Duration::ZERO),
        Canned::chat("ACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("run");
    let out = ask_cut_in(&run, &[], Some(&srv.url));
    assert_eq!(out.status.code(), Some(0), "{}", text(&out));
    // No server: the replies come from the transcript.
    let again = dir.path().join("again");
    let out = ask(
        &["--replay", s(&run.join("transcript.json")), "-o", s(&again)],
        None,
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(
        t.contains("replaying the 4 recorded replies of test-model")
            && t.contains("round 3: the recorded reply (4 of 4)")
            && !t.contains("the prompt differs")
            && t.contains("replay: the same scripts, verdicts and outcome as the recorded run"),
        "{t}"
    );
    for n in 0..4 {
        let f = format!("round_{n}/script.rhai");
        assert_eq!(
            std::fs::read_to_string(run.join(&f)).ok(),
            std::fs::read_to_string(again.join(&f)).ok(),
            "{f}"
        );
    }
    let verdicts = |d: &Path| {
        let v: serde_json::Value =
            serde_json::from_str(&std::fs::read_to_string(d.join("state.json")).unwrap()).unwrap();
        (v["history"].clone(), v["outcome"].clone())
    };
    assert_eq!(verdicts(&run), verdicts(&again));
    assert!(verdicts(&run).0.as_array().unwrap().len() == 2);
    // A recorded run the loop now answers differently: the replay says where, and exits 2.
    let state = run.join("state.json");
    let edited = std::fs::read_to_string(&state)
        .unwrap()
        .replace("\"meets\": true", "\"meets\": false");
    std::fs::write(&state, edited).unwrap();
    let out = ask(
        &[
            "--replay",
            s(&run.join("transcript.json")),
            "-o",
            s(&dir.path().join("third")),
        ],
        None,
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(2), "{t}");
    assert!(
        t.contains("replay differs: sampling round 1: the verdict differs"),
        "{t}"
    );
    // The transcript shared on its own, without its run directory: nothing was compared and
    // nothing said, so a replay that ended otherwise exited 0. Its recorded outcome is
    // compared now, and what could not be is said.
    let alone = dir.path().join("alone");
    std::fs::create_dir(&alone).unwrap();
    let recorded = std::fs::read_to_string(run.join("transcript.json")).unwrap();
    std::fs::write(alone.join("transcript.json"), &recorded).unwrap();
    let out = ask(
        &[
            "--replay",
            s(&alone.join("transcript.json")),
            "-o",
            s(&dir.path().join("fourth")),
        ],
        None,
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(
        t.contains("replay: only the outcome was compared: ")
            && t.contains("has no state.json beside it")
            && !t.contains("replay differs"),
        "{t}"
    );
    let mut v: serde_json::Value = serde_json::from_str(&recorded).unwrap();
    v["outcome"] = serde_json::json!({"RoundsUsed": {"round": 0, "sample": 0}});
    std::fs::write(alone.join("transcript.json"), v.to_string()).unwrap();
    let out = ask(
        &[
            "--replay",
            s(&alone.join("transcript.json")),
            "-o",
            s(&dir.path().join("fifth")),
        ],
        None,
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(2), "{t}");
    assert!(
        t.contains("replay differs: the outcome differs: {\"RoundsUsed\""),
        "{t}"
    );
}

#[test]
fn a_transcript_s_model_and_request_reach_the_terminal_escaped() {
    // A shared transcript's model name and request were printed as they were: an escape
    // sequence cleared the screen, a line break faked a line of drivescript's output.
    let dir = tempfile::tempdir().unwrap();
    let t = dir.path().join("transcript.json");
    let transcript = serde_json::json!({
        "backend": "http",
        "model": "m\u{1b}[2J\nround 0: ACCEPTED",
        "requests": ["vehicle 1 \u{1b}]52;c;ZXZpbA==\u{7} drives slowly"],
        "scene": dir.path().join("absent.yaml"),
        "config": {"context": null, "fixes": 3, "guidance": "output", "lambda": 3.0,
                   "max_agents": 30, "polish": 300, "prompt": {"cot": "designed", "frenet": true},
                   "realism": 1.0, "replan": null, "rounds": 0, "samples": 1,
                   "script_budget": 300.0, "seed": 1, "tolerance": 0.05},
        "records": [{"phase": "llm", "detail": {"reply": "ACCEPT", "request": {"messages": []}}}],
    });
    std::fs::write(&t, transcript.to_string()).unwrap();
    let out = ask(&["--replay", s(&t), "-o", s(&dir.path().join("r"))], None);
    let said = text(&out);
    assert_eq!(out.status.code(), Some(1), "{said}");
    assert!(
        said.contains("replaying the 1 recorded replies of m\\u{001B}[2J\\u{000A}round 0")
            && said.contains("(vehicle 1 \\u{001B}]52;c;ZXZpbA==\\u{0007} drives slowly)"),
        "{said}"
    );
    assert!(
        !said.contains('\u{1b}') && !said.contains('\u{7}'),
        "{said}"
    );
}

#[test]
fn terms_stricter_than_a_passing_checker_are_named_and_relaxing_them_is_accepted() {
    let strict = |tolerance: &str| {
        format!(
            "{}term(\"strict\", 0.1 + 1e-9 * agent(401).x.last(), 1.0{tolerance});\n",
            cut_in_script(401, 399)
        )
    };
    let srv = Server::start(vec![
        Canned::chat(&reply(&strict(""))),
        Canned::chat(&reply(&strict(", 0.2"))),
        Canned::chat("The checker passed and strict is within its tolerance now.\nACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    let feedback = last_user(&srv, 1);
    assert!(
        feedback.contains("The checkers say the request is met in sample")
            && feedback.contains("but your term strict exceeds its tolerance there")
            && feedback.contains("Relax exactly that term")
            && feedback.contains("the checkers say it meets the request, but your terms strict"),
        "{feedback}"
    );
    let report = std::fs::read_to_string(dir.path().join("report.md")).unwrap();
    assert!(
        report.contains("accepted: sample") && report.contains("of round 1"),
        "{report}"
    );
}

#[test]
fn a_term_that_can_never_steer_goes_back_to_the_model_before_any_sampling() {
    // Car 401 drives at 12 m/s: no probe takes it over 60 m/s, so the term is 0 with a zero
    // gradient on every one of them, and guidance could never act on it.
    let dead = "let a = agent(401);\nterm(\"never\", relu(a.speed - 60.0).mean());\n";
    let srv = Server::start(vec![Canned::chat(&reply(dead)), Canned::chat(&reply(dead))]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &["--fixes", "1"], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(2), "{t}");
    let v0 = std::fs::read_to_string(dir.path().join("round_0/validation.txt")).unwrap();
    assert!(
        v0.starts_with("script.rhai:2: term \"never\": it is 0 with a zero gradient")
            && v0.contains("can never steer sampling"),
        "{v0}"
    );
    let back = last_user(&srv, 1);
    assert!(
        back.contains("nothing was sampled")
            && back.contains("term \"never\"")
            && back.contains("can never steer sampling"),
        "{back}"
    );
    for round in ["round_0", "round_1"] {
        assert!(!dir
            .path()
            .join(round)
            .join("USA_US101-3_3_T-1_costs.json")
            .exists());
    }
    let report = std::fs::read_to_string(dir.path().join("report.md")).unwrap();
    assert!(report.contains("Outcome: gave up"), "{report}");
}

#[test]
fn a_request_no_car_can_meet_in_the_horizon_is_said_before_any_round() {
    // Car 394 drives at 14.7 m/s: under 20 km/h (+ the checker's 0.5 m/s) over the first
    // step needs braking at 173 m/s², where a car brakes at 7.
    let srv = Server::start(vec![]);
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join(SCENE);
    let out = ask(
        &[
            s(&scene),
            "vehicle 394 drives below 20 km/h",
            "-o",
            s(dir.path()),
        ],
        Some(&srv.url),
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(2), "{t}");
    let why = "speed_limit (limit=5.556 vehicle=394): vehicle 394 moves at 14.7 m/s (53 km/h) \
               at the current step; the checker wants at most 6.1 m/s";
    assert!(
        t.contains(&format!("cannot be met within the horizon: {why}"))
            && t.contains("needs braking at 172.8 m/s²")
            && t.contains("under the limit from about 1.2 s on")
            && t.contains("nothing was asked or sampled"),
        "{t}"
    );
    assert_eq!(srv.received().len(), 0, "the model was asked");
    assert!(!dir.path().join("round_0").exists());
    let report = std::fs::read_to_string(dir.path().join("report.md")).unwrap();
    assert!(
        report.contains("Outcome: not attempted") && report.contains(why),
        "{report}"
    );
    // Below 50 km/h it needs 6 m/s², within a car's braking: the first round is asked.
    let run = tempfile::tempdir().unwrap();
    let out = ask(
        &[
            s(&scene),
            "vehicle 394 drives below 50 km/h",
            "--llm",
            "manual",
            "-o",
            s(run.path()),
        ],
        None,
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(
        !t.contains("cannot be met") && t.contains("waiting for a reply"),
        "{t}"
    );
    assert!(run.path().join("round_0/prompt.md").exists());
}

#[test]
fn ask_and_the_batch_table_give_one_verdict_when_the_checker_passes_but_a_term_does_not() {
    // Under 120 km/h every sample of car 401 (12 m/s) passes the checker, while the script's
    // own term stays near 0.1, over the 0.05 tolerance: the request is met, the script asks for
    // more. `ask` once exited 2 (not met) on such a pair while the batch table counted it.
    let strict = "let a = agent(401);\nterm(\"strict\", 0.1 + 1e-9 * a.x.last());\n";
    let srv = Server::start(vec![
        Canned::chat(&reply(strict)),
        Canned::chat(&reply(strict)),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join(SCENE);
    let request = "vehicle 401 drives below 120 km/h";
    let single = dir.path().join("single");
    let out = ask(
        &[s(&scene), request, "--rounds", "0", "-o", s(&single)],
        Some(&srv.url),
    );
    let t = text(&out);
    let costs: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(single.join("round_0/USA_US101-3_3_T-1_costs.json")).unwrap(),
    )
    .unwrap();
    for o in costs["samples"].as_array().unwrap() {
        assert_eq!(o["verdicts"][0]["passed"], true, "{o}");
        // 0.1 and a gradient too small to move it: a constant is refused as a dead term.
        let f = o["terms"][0]["final"].as_f64().unwrap();
        assert!((f - 0.1).abs() < 1e-6, "{o}");
    }
    assert!(t.contains("none of its samples meets the request"), "{t}");
    let verdict = "succeeded: round 0 met by the checkers (script terms over tolerance)";
    assert!(t.contains(&format!("Verdict: {verdict}.")), "{t}");
    assert_eq!(out.status.code(), Some(0), "{t}");
    // The same pair in a batch: the table and the pair's line say the same.
    let file = dir.path().join("pairs.yaml");
    std::fs::write(
        &file,
        format!(
            "entries:\n  - scene: {}\n    request: \"{request}\"\n",
            scene.display()
        ),
    )
    .unwrap();
    let out_dir = dir.path().join("batch");
    let out = ask(
        &["--batch", s(&file), "--rounds", "0", "-o", s(&out_dir)],
        Some(&srv.url),
    );
    let t = text(&out);
    assert!(out.status.success(), "{t}");
    assert!(t.contains(verdict), "{t}");
    let summary: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(out_dir.join("summary.json")).unwrap())
            .unwrap();
    assert_eq!(summary["instances"][0]["verdict"]["text"], verdict);
    assert_eq!(summary["instances"][0]["verdict"]["succeeded"], true);
    assert_eq!(summary["rows"][0]["label"], "speed_limit");
    assert_eq!(summary["rows"][0]["passed"][0], 1);
}

#[test]
fn an_accept_refused_in_the_last_round_gets_a_turn_to_accept_the_answer() {
    // One refinement round: the idle script fails, its ACCEPT is refused, and the cut-in that
    // answers the refusal is the last sampling. It meets the request, so the model gets one
    // more turn to accept it; the run once ended "(not accepted)" here.
    let srv = Server::start(vec![
        Canned::chat(&reply(IDLE)),
        Canned::chat("ACCEPT"),
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat("The cut-in passes now.\nACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &["--rounds", "1"], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert_eq!(srv.received().len(), 4, "{t}");
    assert!(t.contains("one more turn to accept it"), "{t}");
    let last = last_user(&srv, 3);
    assert!(
        last.contains("The rounds are used up (--rounds 1)") && last.contains("Reply ACCEPT"),
        "{last}"
    );
    let report = std::fs::read_to_string(dir.path().join("report.md")).unwrap();
    assert!(
        report.contains("accepted: sample") && report.contains("of round 2"),
        "{report}"
    );
    assert!(!t.contains("(not accepted)"), "{t}");
}

#[test]
fn a_password_or_key_in_the_url_gets_into_no_output_and_no_file() {
    // The key as a query with no path before it (once kept whole in messages and files, and
    // the endpoint appended to the query), and as the URL's password, echoed as the server got
    // it: in the query, and as the `Basic` token of "u:pw-url-secret-1".
    let srv = Server::start(vec![Canned::raw(
        400,
        r#"{"error": {"message": "you sent key=sk-query-secret, Basic dTpwdy11cmwtc2VjcmV0LTE= (pw-url-secret-1)"}}"#,
    )]);
    let port = srv
        .url
        .trim_start_matches("http://127.0.0.1:")
        .trim_end_matches("/v1");
    let url = format!("http://u:pw-url-secret-1@127.0.0.1:{port}?key=sk-query-secret");
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(t.contains("you sent key=[redacted]"), "{t}");
    assert_eq!(
        srv.received()[0].path,
        "/chat/completions?key=sk-query-secret"
    );
    for e in walk(dir.path())
        .iter()
        .map(|p| std::fs::read(p).unwrap())
        .chain([t.into_bytes()])
    {
        let e = String::from_utf8_lossy(&e);
        for secret in [
            "sk-query-secret",
            "pw-url-secret-1",
            "dTpwdy11cmwtc2VjcmV0LTE=",
        ] {
            assert!(!e.contains(secret), "{secret} in {e}");
        }
    }
}

#[test]
fn escape_sequences_a_server_sends_reach_no_terminal() {
    // In an error: the screen cleared, the window retitled, a carriage return over the line.
    let srv = Server::start(vec![Canned::raw(
        400,
        r#"{"error": {"message": "bad\u001b[2J\u001b]0;pwned\u0007\rall good"}}"#,
    )]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &[], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(!t.contains(['\u{1b}', '\u{7}', '\r']), "{t:?}");
    assert!(t.contains("bad\\u{001B}[2J"), "{t}");
    // In a reply's plan, printed as the round's progress.
    let srv = Server::start(vec![Canned::chat(&format!(
        "1. Events\u{1b}]52;c;cHduZWQ=\u{7}: one cut-in.\n\n```rhai\n{}```\n",
        cut_in_script(401, 399)
    ))]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(dir.path(), &["--rounds", "0"], Some(&srv.url));
    let t = text(&out);
    assert!(t.contains("Events\\u{001B}]52;c;"), "{t}");
    assert!(!t.contains(['\u{1b}', '\u{7}']), "{t:?}");
}

#[test]
fn a_model_or_url_no_backend_asks_is_an_error_not_dropped() {
    // `--model` alone ran the rules planner, announced as "none configured"; with --llm rules
    // or manual, --llm-url and --model were dropped without a word.
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join(SCENE);
    for (extra, want) in [
        (
            &["--model", "m"][..],
            "an LLM model is set but no server URL",
        ),
        (
            &["--llm", "rules", "--llm-url", "http://127.0.0.1:1/v1"],
            "--llm-url: --llm rules asks no server",
        ),
        (
            &["--llm", "manual", "--model", "m"],
            "--model: --llm manual asks no server",
        ),
    ] {
        let run = dir.path().join("run");
        let out = ask(
            &[&[s(&scene), REQUEST, "-o", s(&run)][..], extra].concat(),
            None,
        );
        let t = text(&out);
        assert_eq!(out.status.code(), Some(1), "{extra:?}: {t}");
        assert!(t.contains(want), "{extra:?}: {t}");
        assert!(!run.join("round_0").exists(), "{extra:?}: {t}");
    }
}

#[test]
fn a_flag_the_chosen_backend_does_not_read_is_an_error_not_dropped() {
    // `--llm rules --temperature 1.5 --max-tokens-field "x y" -v` ran the rules planner, exit
    // 0: none of the three did anything. A flag given with its default value is still given.
    let dir = tempfile::tempdir().unwrap();
    let scene = samples().join(SCENE);
    let run = dir.path().join("run");
    let fresh = |extra: &[&str]| {
        ask(
            &[&[s(&scene), REQUEST, "-o", s(&run)][..], extra].concat(),
            None,
        )
    };
    for (extra, want) in [
        (
            &[
                "--llm",
                "rules",
                "--temperature",
                "1.5",
                "--max-tokens-field",
                "x y",
                "-v",
            ][..],
            "--max-tokens-field \"x y\": a request field name is ASCII letters, digits and `_`",
        ),
        (
            &["--llm", "rules", "--temperature", "0.2"],
            "--temperature: --llm rules asks no server",
        ),
        (
            &["--llm", "rules", "--max-tokens-field", "max_tokens"],
            "--max-tokens-field: --llm rules asks no server",
        ),
        (
            &["--llm", "rules", "--context", "8192"],
            "--context: --llm rules sends no prompt to a model",
        ),
        (
            &["--llm", "rules", "--no-frenet"],
            "--no-frenet: --llm rules sends no prompt to a model",
        ),
        (&["--llm", "rules", "-v"], "-v/--verbose: only --batch"),
        (
            &["--attempts", "3"],
            "--attempts: the rules planner (--llm auto's choice: no server is configured",
        ),
        (
            &["--llm", "manual", "--no-stream"],
            "--no-stream: --llm manual asks no server",
        ),
        (
            &["--llm", "manual", "--max-tokens", "100"],
            "--max-tokens: --llm manual asks no server; --max-tokens sets only the reply's \
             share of the --context window",
        ),
        (
            &["--llm", "manual", "--max-tokens-field", "model"],
            "--max-tokens-field \"model\": the request already sends that field",
        ),
    ] {
        let out = fresh(extra);
        let t = text(&out);
        assert_eq!(out.status.code(), Some(1), "{extra:?}: {t}");
        assert!(t.contains(want), "{extra:?}: {t}");
        assert!(!run.exists(), "{extra:?}: {t}");
    }
    // What a manual run does read: the prompt's flags, and --max-tokens with --context.
    let out = fresh(&[
        "--llm",
        "manual",
        "--context",
        "8192",
        "--max-tokens",
        "1000",
        "--no-cot",
    ]);
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    assert!(t.contains("1000 for the reply"), "{t}");
    // A run taken up again keeps its settings and backend.
    let d = s(&run);
    for (args, want) in [
        (
            &["--resume", d, "--rounds", "5"][..],
            "--rounds: --resume goes on with the settings the run started with",
        ),
        (
            &["--continue", d, "make it abrupt", "--no-cot"],
            "--no-cot: --continue goes on with the settings the run started with",
        ),
        (
            &["--resume", d, "--temperature", "1"],
            "--temperature: the run's backend, manual, asks no server",
        ),
        (&["--resume", d, "-o", d], "-o: --resume DIR goes on in DIR"),
        (
            &["--replay", "t.json", "-o", d, "--seed", "2"],
            "--seed: --replay asks no backend",
        ),
    ] {
        let out = ask(args, None);
        let t = text(&out);
        assert_eq!(out.status.code(), Some(1), "{args:?}: {t}");
        assert!(t.contains(want), "{args:?}: {t}");
    }
    assert!(!run.join("round_1").exists());
}

/// A run whose model's script failed validation, taken up with `--llm rules`: the rules
/// planner has written no script yet, so it writes its own; it does not give up blaming "the
/// rules planner's script" for the model's. Where it has written one that fails, the message
/// says so.
#[test]
fn the_rules_planner_taking_over_a_run_is_not_blamed_for_the_models_script() {
    let srv = Server::start(vec![
        Canned::chat(&reply(&cut_in_script(401, 9999))),
        Canned::raw(503, "Service Unavailable"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(
        dir.path(),
        &["--attempts", "1", "--rounds", "0"],
        Some(&srv.url),
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains("round 0: validation failed") && t.contains("HTTP 503"),
        "{t}"
    );
    let out = ask(&["--resume", s(dir.path()), "--llm", "rules"], None);
    let t = text(&out);
    assert!(!t.contains("rules planner's script"), "{t}");
    assert!(
        t.contains("Plan (rules planner)") && t.contains("round 1: validating"),
        "{t}"
    );
    assert!(matches!(out.status.code(), Some(0 | 2)), "{t}");
}

/// `--continue` on a run with `--context 4096` after two rounds: every request it sends is
/// fitted to the window, as a fresh run's are, and each still carries the follow-up request.
/// Its second round stopped with "the conversation does not fit --context 4096 ... raise
/// --context", after sampling the first, advising a flag --continue refuses; and the rounds it
/// did send had summarised the follow-up to "drivescript answered: # Follow-up request".
#[test]
fn a_continued_run_fits_its_context_and_keeps_the_follow_up_in_every_request() {
    use drivescript::llm::budget::estimate_tokens;
    const FOLLOW_UP: &str = "vehicle 405 drives off the road";
    let srv = Server::start(vec![
        Canned::chat(&reply(IDLE)),
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat("ACCEPT"),
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat("ACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(
        dir.path(),
        &["--context", "4096", "--rounds", "2"],
        Some(&srv.url),
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(0), "{t}");
    let before = srv.received().len();
    let out = ask(&["--continue", s(dir.path()), FOLLOW_UP], Some(&srv.url));
    let t = text(&out);
    assert!(matches!(out.status.code(), Some(0 | 2)), "{t}");
    assert!(!t.contains("does not fit"), "{t}");
    let received = srv.received();
    assert!(received.len() >= before + 2, "{t}");
    for (k, r) in received.iter().enumerate().skip(before) {
        let body = r.json();
        assert_eq!(body["max_tokens"], 1024);
        let msgs: Vec<Message> = serde_json::from_value(body["messages"].clone()).unwrap();
        let tokens = estimate_tokens(&msgs);
        assert!(tokens <= 3072, "request {k}: {tokens} tokens\n{t}");
        assert!(
            msgs.iter().any(|m| m.content.contains(FOLLOW_UP)),
            "request {k} lost the follow-up:\n{:#?}",
            msgs.iter()
                .map(|m| &m.content[..m.content.len().min(300)])
                .collect::<Vec<_>>()
        );
        assert!(msgs[1].content.contains(REQUEST), "request {k}");
    }
}

/// A continued run whose window cannot hold what it must send is refused before anything is
/// sent or saved, naming --context and the sizes, and advising what --continue allows (a new
/// run): it advised "raise --context", which --continue refuses.
#[test]
fn a_continuation_its_window_cannot_hold_is_refused_before_sending_with_advice_that_fits() {
    use drivescript::llm::fit::Window;
    use drivescript::llm::session::first_messages;
    use drivescript::llm::{Prompts, SessionConfig};
    let root = Path::new(env!("CARGO_MANIFEST_DIR"));
    let prompts = Prompts::load(&root.join("prompts")).unwrap();
    let scene = drivescript::io::load_scene(
        &samples().join(SCENE),
        0,
        &drivescript::io::LoadOptions::default(),
    )
    .unwrap();
    // The smallest first prompt, from the message that refuses a window too small for it.
    let tiny = SessionConfig {
        context: Some(Window {
            tokens: 600,
            reply: 150,
        }),
        ..SessionConfig::default()
    };
    let e = first_messages(&prompts, &tiny, &scene, &[REQUEST.to_string()], horizon())
        .unwrap_err()
        .to_string();
    let smallest: u64 = e
        .split("takes about ")
        .nth(1)
        .and_then(|r| r.split(' ').next())
        .and_then(|n| n.parse().ok())
        .unwrap_or_else(|| panic!("{e}"));
    // Room for that prompt and little more: the run's one round fits, a follow-up does not.
    let context = (smallest + 200 + 40).to_string();
    let srv = Server::start(vec![
        Canned::chat(&reply(&cut_in_script(401, 399))),
        Canned::chat("ACCEPT"),
    ]);
    let dir = tempfile::tempdir().unwrap();
    let out = ask_cut_in(
        dir.path(),
        &[
            "--context",
            &context,
            "--max-tokens",
            "200",
            "--rounds",
            "0",
        ],
        Some(&srv.url),
    );
    let t = text(&out);
    assert!(matches!(out.status.code(), Some(0 | 2)), "{t}");
    let sent = srv.received().len();
    let state = std::fs::read(dir.path().join("state.json")).unwrap();
    let out = ask(
        &[
            "--continue",
            s(dir.path()),
            "vehicle 405 drives off the road",
        ],
        Some(&srv.url),
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(1), "{t}");
    assert!(
        t.contains(&format!("does not fit --context {context} ("))
            && t.contains("tokens for the prompt after 200 for the reply")
            && t.contains("it takes about ")
            && t.contains("start a new run (-o NEWDIR) with a larger --context"),
        "{t}"
    );
    assert!(
        !t.contains("raise --context") && !t.contains("lower --max-tokens"),
        "{t}"
    );
    assert_eq!(srv.received().len(), sent, "{t}");
    assert_eq!(std::fs::read(dir.path().join("state.json")).unwrap(), state);
}

/// `--resume` of a manual run with `--max-tokens`: refused without advising --context, which
/// --resume refuses too ("--context is not given").
#[test]
fn a_resumed_manual_run_refuses_max_tokens_without_advising_context() {
    let dir = tempfile::tempdir().unwrap();
    let d = s(dir.path());
    let out = ask(
        &[
            s(&samples().join(SCENE)),
            REQUEST,
            "-o",
            d,
            "--llm",
            "manual",
        ],
        None,
    );
    assert_eq!(out.status.code(), Some(0), "{}", text(&out));
    for mode in [vec!["--resume", d], vec!["--resume", d, "--llm", "manual"]] {
        let out = ask(&[&mode[..], &["--max-tokens", "100"]].concat(), None);
        let t = text(&out);
        assert_eq!(out.status.code(), Some(1), "{t}");
        assert!(
            t.contains("--max-tokens: ")
                && t.contains("asks no server")
                && t.contains("--resume goes on with the run's (its state.json)"),
            "{t}"
        );
        assert!(!t.contains("--context is not given"), "{t}");
    }
}

/// A chunk size line that is not hex said "request or response body error" twice: an io
/// error shows its inner error's text, and both layers were joined.
#[test]
fn a_malformed_chunked_reply_names_each_cause_once() {
    use std::io::Write;
    let url = common::llm_server::one_shot(
        b"HTTP/1.1 200 OK\r\nContent-Type: application/json\r\nTransfer-Encoding: chunked\r\n\r\n",
        |stream| {
            let _ = stream.write_all(b"ZZ\r\n{\"x\":1}\r\n0\r\n\r\n");
        },
    );
    let e = ask_one(&client(&url)).unwrap_err().to_string();
    assert!(
        e.contains("reading the reply") && e.contains("chunk size"),
        "{e}"
    );
    assert_eq!(
        e.matches("request or response body error").count(),
        1,
        "{e}"
    );
}

/// A refusal or a tool call (streamed or not) was called an empty reply, asked for again up
/// to --fixes times, or "no message content (a refusal or a tool call?)" without the model's
/// words; streamed content parts were dropped; a chunk of a second choice was appended to the
/// reply; a reply the server stopped itself (`finish_reason: "abort"`) went back to the model
/// as its own unclosed script; a byte order mark before a JSON body made it "not JSON".
#[test]
fn refusals_tool_calls_content_parts_and_other_choices_are_read_for_what_they_are() {
    use serde_json::json;
    let ev = |v: serde_json::Value| v.to_string();
    let stop = || ev(json!({"choices": [{"index": 0, "delta": {}, "finish_reason": "stop"}]}));
    let srv = Server::start(vec![
        Canned::events(
            vec![
                ev(json!({"choices": [{"index": 0, "delta": {"role": "assistant", "refusal": ""}}]})),
                ev(json!({"choices": [{"index": 0, "delta": {"refusal": "I can't help with crashes."}}]})),
                stop(),
                "[DONE]".into(),
            ],
            Duration::ZERO,
        ),
        Canned::raw(
            200,
            &json!({"choices": [{"index": 0, "message": {"role": "assistant", "content": null, "refusal": "No, sorry."}, "finish_reason": "stop"}]})
                .to_string(),
        ),
        Canned::events(
            vec![
                ev(json!({"choices": [{"index": 0, "delta": {"tool_calls": [{"index": 0, "id": "c", "type": "function", "function": {"name": "run_code", "arguments": ""}}]}}]})),
                ev(json!({"choices": [{"index": 0, "delta": {}, "finish_reason": "tool_calls"}]})),
                "[DONE]".into(),
            ],
            Duration::ZERO,
        ),
        Canned::raw(
            200,
            &json!({"choices": [{"message": {"content": null, "tool_calls": [{"id": "c", "type": "function", "function": {"name": "search", "arguments": "{}"}}]}, "finish_reason": "tool_calls"}]})
                .to_string(),
        ),
        Canned::events(
            vec![
                ev(json!({"choices": [{"index": 0, "delta": {"content": [{"type": "text", "text": "ACC"}]}}]})),
                ev(json!({"choices": [{"index": 0, "delta": {"content": "EPT"}}]})),
                stop(),
                "[DONE]".into(),
            ],
            Duration::ZERO,
        ),
        Canned::events(
            vec![
                ev(json!({"choices": [{"index": 0, "delta": {"content": "ACCEPT"}}]})),
                ev(json!({"choices": [{"index": 1, "delta": {"content": " and more"}}]})),
                stop(),
                "[DONE]".into(),
            ],
            Duration::ZERO,
        ),
        Canned::events(
            vec![
                ev(json!({"choices": [{"index": 0, "delta": {"content": "```rhai\nlet a"}}]})),
                ev(json!({"choices": [{"index": 0, "delta": {}, "finish_reason": "abort"}]})),
                "[DONE]".into(),
            ],
            Duration::ZERO,
        ),
        Canned::raw(
            200,
            &format!(
                "\u{feff}{}",
                json!({"choices": [{"message": {"content": "ACCEPT"}, "finish_reason": "stop"}]})
            ),
        ),
    ]);
    let c = client(&srv.url);
    for want in [
        "the model refused to answer: \"I can't help with crashes.\"",
        "the model refused to answer: \"No, sorry.\"",
        "a call of the tool run_code and no text",
        "a call of the tool search and no text",
    ] {
        let e = ask_one(&c).unwrap_err().to_string();
        assert!(e.contains(want), "{want}: {e}");
    }
    assert_eq!(ask_one(&c).unwrap().reply, "ACCEPT");
    assert_eq!(ask_one(&c).unwrap().reply, "ACCEPT");
    let e = ask_one(&c).unwrap_err();
    assert!(
        matches!(e, LlmError::Reset { .. })
            && e.to_string().contains("finish_reason \"abort\"")
            && e.to_string().contains("after 1 tokens"),
        "{e}"
    );
    assert_eq!(ask_one(&c).unwrap().reply, "ACCEPT");
}

/// A stream that begins with a byte order mark lost its first event (for some servers the
/// whole reply: "the reply is empty"); a JSON body labelled as an event stream was read as
/// events and called "ended after 0 tokens", as if the server had died.
#[test]
fn a_stream_after_a_byte_order_mark_and_json_labelled_as_a_stream_are_read_whole() {
    use std::io::Write;
    let chunk = serde_json::json!({"choices": [{"index": 0, "delta": {"content": "ACCEPT"}, "finish_reason": "stop"}]});
    let body = format!("\u{feff}data: {chunk}\n\ndata: [DONE]\n\n");
    let url = common::llm_server::one_shot(
        b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nConnection: close\r\n\r\n",
        move |stream| {
            let _ = stream.write_all(body.as_bytes());
            let _ = stream.shutdown(std::net::Shutdown::Both);
        },
    );
    assert_eq!(ask_one(&client(&url)).unwrap().reply, "ACCEPT");
    let json = serde_json::json!({"choices": [{"message": {"content": "ACCEPT"}, "finish_reason": "stop"}]})
        .to_string();
    let head = format!(
        "HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nContent-Length: {}\r\n\r\n",
        json.len()
    );
    let url = common::llm_server::one_shot(
        Box::leak(head.into_bytes().into_boxed_slice()),
        move |stream| {
            let _ = stream.write_all(json.as_bytes());
        },
    );
    assert_eq!(ask_one(&client(&url)).unwrap().reply, "ACCEPT");
    // An error event's message was dropped: "the event stream ended after 0 tokens".
    let url = common::llm_server::one_shot(
        b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nConnection: close\r\n\r\n",
        |stream| {
            let _ =
                stream.write_all(b"event: error\ndata: {\"message\": \"upstream overloaded\"}\n\n");
            let _ = stream.shutdown(std::net::Shutdown::Both);
        },
    );
    let e = ask_one(&client(&url)).unwrap_err().to_string();
    assert!(
        e.contains("an error event after 0 tokens: upstream overloaded"),
        "{e}"
    );
}

/// A streamed refusal was an empty reply, asked for again until --fixes ran out (four paid
/// requests, each refused alike); as an error it would stop a batch at that pair however
/// often the batch was run again. The run now gives up at once, exit 2, in the model's words.
#[test]
fn a_refusal_ends_the_run_after_one_request_in_the_model_s_words() {
    let refusal = serde_json::json!({"choices": [{"index": 0, "delta": {"refusal": "I won't stage a crash."}}]});
    let stop = serde_json::json!({"choices": [{"index": 0, "delta": {}, "finish_reason": "stop"}]});
    let srv = Server::start(vec![Canned::events(
        vec![refusal.to_string(), stop.to_string(), "[DONE]".into()],
        Duration::ZERO,
    )]);
    let dir = tempfile::tempdir().unwrap();
    let run = dir.path().join("r");
    let out = ask_cut_in(&run, &["--samples", "1"], Some(&srv.url));
    let t = text(&out);
    assert_eq!(out.status.code(), Some(2), "{t}");
    assert!(
        t.contains("gave up")
            && t.contains("the model refused to answer: \"I won't stage a crash.\""),
        "{t}"
    );
    assert_eq!(srv.received().len(), 1, "{t}");
    assert_no_key(&run);
    // The request is a call the run made: recorded, counted, and given up on in a replay
    // (the report said "LLM calls: 0", and the transcript held nothing to replay).
    let report = std::fs::read_to_string(run.join("report.md")).unwrap();
    assert!(report.contains("LLM calls: 1."), "{report}");
    let transcript: serde_json::Value =
        serde_json::from_slice(&std::fs::read(run.join("transcript.json")).unwrap()).unwrap();
    let llm: Vec<&serde_json::Value> = transcript["records"]
        .as_array()
        .unwrap()
        .iter()
        .filter(|r| r["phase"] == "llm")
        .collect();
    assert_eq!(llm.len(), 1, "{transcript}");
    assert!(
        llm[0]["detail"]["refused"]
            .as_str()
            .is_some_and(|m| m.contains("I won't stage a crash.")),
        "{transcript}"
    );
    assert!(llm[0]["detail"]["request"]["messages"].is_array());
    let again = dir.path().join("again");
    let out = ask(
        &["--replay", s(&run.join("transcript.json")), "-o", s(&again)],
        None,
    );
    let t = text(&out);
    assert_eq!(out.status.code(), Some(2), "{t}");
    assert!(
        t.contains("the model refused to answer: \"I won't stage a crash.\"")
            && t.contains("replay: the same scripts, verdicts and outcome as the recorded run"),
        "{t}"
    );
}

/// `vehicle {cutter} cuts in front of vehicle {cutter}` with `behaviour: cut_in` ran: the
/// victim the checker judged was chosen for each scene and named nowhere in the request, and
/// every pair counted as a failure of the loop ("not planned"), exit 0.
#[test]
fn a_batch_request_that_leaves_out_a_role_its_checker_judges_is_refused() {
    let (_dir, out, t) = refused_rules_batch(
        "  - request: \"vehicle {cutter} cuts in front of vehicle {cutter}\"\n    behaviour: cut_in\n",
    );
    assert!(
        t.contains(
            "entry on line 3: the request names no {victim}, an agent cut_in's checker judges"
        ) && t.contains("{cutter}, {victim}"),
        "{t}"
    );
    assert!(!out.join("runs").exists(), "{t}");
}

/// `Retry-After` may be an HTTP date (`Wed, 21 Oct 2099 07:28:00 GMT`) as well as seconds: the
/// date was ignored, and the request retried after the plain backoff without a word.
#[test]
fn a_retry_after_given_as_an_http_date_is_honoured_like_seconds() {
    let srv = Server::start(vec![
        Canned::raw(503, r#"{"error": {"message": "busy"}}"#)
            .header("Retry-After", "Wed, 21 Oct 2099 07:28:00 GMT"),
        Canned::raw(503, r#"{"error": {"message": "busy"}}"#)
            .header("Retry-After", "Wed, 21 Oct 2015 07:28:00 GMT"),
        Canned::chat("after the waits"),
    ]);
    let mut cfg = HttpConfig::new(&srv.url, "m");
    cfg.backoff = Duration::from_millis(20);
    cfg.backoff_max = Duration::from_millis(300);
    let ex = ask_one(&HttpClient::new(cfg).unwrap()).unwrap();
    assert_eq!(ex.reply, "after the waits");
    // 2099 is decades away: cut to the ceiling, and said; 2015 is past: no wait at all.
    assert!(
        ex.retries[0].contains("Retry-After asked: capped at the backoff ceiling")
            && ex.retries[0].contains("(waited 0.3 s"),
        "{:?}",
        ex.retries
    );
    assert!(
        ex.retries[1].contains("(waited 0.0 s, as Retry-After asked)"),
        "{:?}",
        ex.retries
    );
}

/// A `--prompts` folder that is not there was "prompt template /nowhere/system.md: cannot read
/// it: No such file or directory", as if one template of it were missing.
#[test]
fn a_prompt_folder_that_is_missing_or_a_file_is_named_as_such() {
    let dir = tempfile::tempdir().unwrap();
    let file = dir.path().join("prompts.md");
    std::fs::write(&file, "x").unwrap();
    for (folder, why) in [
        (dir.path().join("nowhere"), "does not exist"),
        (file, "is a file, not a folder"),
    ] {
        let err = common::fails(&[
            "prompt",
            "show",
            s(&samples().join(SCENE)),
            REQUEST,
            "--prompts",
            s(&folder),
        ]);
        assert!(
            err.contains(&format!(
                "the prompt folder {} (--prompts) {why}",
                s(&folder)
            )) && !err.contains("system.md: cannot read it"),
            "{err}"
        );
    }
}

/// A reply naming a key twice in one object (two `choices`, a message with two `content`s)
/// was read as its last copy without a word, though other readers (a proxy between) take the
/// first: a reply holding two answers is no answer. Scene, rollout and checkpoint files refuse
/// the same.
#[test]
fn a_reply_naming_a_key_twice_is_refused_not_read_as_its_last_copy() {
    let choice = |c: &str| {
        format!(
            r#"{{"index": 0, "message": {{"role": "assistant", "content": "{c}"}}, "finish_reason": "stop"}}"#
        )
    };
    let choices_twice = format!(
        r#"{{"choices": [{}], "choices": [{}]}}"#,
        choice("ACCEPT"),
        choice("x")
    );
    let content_twice = r#"{"choices": [{"index": 0, "message": {"role": "assistant", "content": "ACCEPT", "content": "x"}, "finish_reason": "stop"}]}"#;
    for (body, key) in [
        (choices_twice.as_str(), "choices"),
        (content_twice, "content"),
    ] {
        let srv = Server::start(vec![Canned::raw(200, body)]);
        let mut cfg = HttpConfig::new(&srv.url, "m");
        cfg.stream = false;
        let e = ask_one(&HttpClient::new(cfg).unwrap())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains(&format!(
                "the reply holds the key \"{key}\" twice in one object"
            )),
            "{e}"
        );
    }
    let event = r#"{"choices": [{"index": 0, "delta": {"content": "ACCEPT", "content": "x"}}]}"#;
    let srv = Server::start(vec![Canned::events(
        vec![event.into(), "[DONE]".into()],
        Duration::ZERO,
    )]);
    let mut cfg = HttpConfig::new(&srv.url, "m");
    cfg.stream = true;
    let e = ask_one(&HttpClient::new(cfg).unwrap())
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("a stream event holds the key \"content\" twice in one object"),
        "{e}"
    );
}

/// A scene whose steps are not 0.1 s apart cannot be sampled by the 10 Hz model; ask sent the
/// model its request (a paid request) and got a script before the first round's sampling
/// refused it. It is refused before any request, and no run directory is made.
#[test]
fn ask_refuses_a_scene_of_another_time_step_before_asking_the_model() {
    let dir = tempfile::tempdir().unwrap();
    let xml = std::fs::read_to_string(samples().join(SCENE)).unwrap();
    assert!(xml.contains("timeStepSize=\"0.1\""));
    let scene = dir.path().join("slow.xml");
    std::fs::write(
        &scene,
        xml.replacen("timeStepSize=\"0.1\"", "timeStepSize=\"0.5\"", 1),
    )
    .unwrap();
    let srv = Server::start(vec![Canned::chat(&reply("term(\"x\", 0.0);\n"))]);
    let out = dir.path().join("run");
    let o = ask(&[s(&scene), REQUEST, "-o", s(&out)], Some(&srv.url));
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("slow.xml: scene") && t.contains("its steps are 0.5 s apart"),
        "{t}"
    );
    assert!(srv.received().is_empty(), "{t}");
    assert!(!out.exists(), "{t}");
}

/// `ask --samples N` with more samples than the scene's sampling batch fits in memory was
/// refused only when round 0 began to sample: after the run directory was made and the model
/// asked (and paid). It is refused with the flags, before either, alone or in a batch.
#[test]
fn ask_refuses_more_samples_than_fit_before_asking_the_model() {
    let dir = tempfile::tempdir().unwrap();
    // 120 vehicles on a six-lane road: many windows, so 1,024 samples are past the budget.
    let scene = common::crowd_scene(dir.path());
    let srv = Server::start(vec![Canned::chat(&reply("term(\"x\", 0.0);\n"))]);
    let out = dir.path().join("run");
    let request = "vehicle 21 cuts in front of vehicle 2";
    let o = ask(
        &[s(&scene), request, "-o", s(&out), "--samples", "1024"],
        Some(&srv.url),
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("--samples 1024: samples = 1024: the scene takes")
            && t.contains("samples of this scene fit"),
        "{t}"
    );
    assert!(srv.received().is_empty(), "{t}");
    assert!(!out.exists(), "{t}");
    let file = dir.path().join("requests.yaml");
    std::fs::write(
        &file,
        format!(
            "scenes: {}\nentries:\n  - request: \"{request}\"\n    behaviour: cut_in\n    params: {{cutter: 21, victim: 2}}\n",
            scene.display()
        ),
    )
    .unwrap();
    let o = ask(
        &["--batch", s(&file), "-o", s(&out), "--samples", "1024"],
        Some(&srv.url),
    );
    let t = text(&o);
    assert_eq!(o.status.code(), Some(1), "{t}");
    assert!(
        t.contains("crowd.yaml") && t.contains("--samples 1024: samples = 1024"),
        "{t}"
    );
    assert!(srv.received().is_empty(), "{t}");
    assert!(!out.exists(), "{t}");
}
