//! `ask --replay TRANSCRIPT`: a recorded run asked again of its transcript instead of a server.
//!
//! A run's `transcript.json` holds every request body and every reply; replayed in a new run
//! directory, the same replies meet the same prompts, the same scripts are validated and
//! sampled with the same seed, and the verdicts should come out the same. A run a user had with
//! their model thus becomes a regression test with no network: [`compare`] lists where the
//! replay differs from the original (a script, a round's verdict, the outcome), and a prompt
//! that changed since the recording is said as it is sent.

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::io::plain_types;

use super::client::Message;
use super::session::{SessionConfig, StoredCheck, MAX_RUN_FILE_BYTES};
use super::LlmError;

/// One recorded exchange.
#[derive(Debug, Clone, PartialEq)]
pub struct Exchange {
    /// The messages that were sent.
    pub messages: Vec<Message>,
    /// What came back (empty where the model refused).
    pub reply: String,
    /// The model's refusal, where it refused: the run gave up on it, and so does the replay.
    pub refused: Option<String>,
    /// The transcript's record of it (usage, latency, ...), kept in the replay's transcript.
    pub detail: Value,
}

/// A transcript, read for replaying.
#[derive(Debug, Clone)]
pub struct Recorded {
    /// The transcript file.
    pub path: PathBuf,
    /// The scene the run was on.
    pub scene: PathBuf,
    /// Its request.
    pub request: String,
    /// Its settings.
    pub config: SessionConfig,
    /// The model that answered.
    pub model: Option<String>,
    /// The checkers, from the run's `state.json` where it lies beside the transcript (a batch
    /// pair's are given, not read from the request).
    pub checks: Option<Vec<StoredCheck>>,
    /// The exchanges with the server, in order.
    pub exchanges: Vec<Exchange>,
}

fn bad(path: &Path, message: impl Into<String>) -> LlmError {
    LlmError::Input {
        path: path.to_path_buf(),
        message: message.into(),
    }
}

fn read_json(path: &Path) -> Result<Value, LlmError> {
    let text = crate::io::read_regular_text(path, MAX_RUN_FILE_BYTES, "a run's file")
        .map_err(|e| bad(path, format!("cannot read it: {}", e.reason())))?;
    // A key named twice (a reply, a request) was read as its last copy without a word.
    crate::io::json::parse_json(&text).map_err(|e| bad(path, format!("not JSON ({e})")))
}

/// Reads a transcript for [`super::Backend::Replay`]: only a run that asked a server holds the
/// replies, and only a run of one request (a follow-up changes the conversation mid-way).
pub fn read_transcript(path: &Path) -> Result<Recorded, LlmError> {
    let t = read_json(path)?;
    if t["backend"] != "http" {
        return Err(bad(
            path,
            format!(
                "the run's backend is {}: only a run that asked a server (--llm http) records \
                 the replies a replay needs",
                t["backend"]
            ),
        ));
    }
    let requests: Vec<String> = serde_json::from_value(t["requests"].clone()).map_err(|e| {
        bad(
            path,
            format!("\"requests\": {}", plain_types(&e.to_string())),
        )
    })?;
    let [request] = requests.as_slice() else {
        return Err(bad(
            path,
            format!(
                "the run has {} requests: replaying a run with follow-ups (--continue) is not \
                 supported; replay the run before them",
                requests.len()
            ),
        ));
    };
    let config: SessionConfig = serde_json::from_value(t["config"].clone())
        .map_err(|e| bad(path, format!("\"config\": {}", plain_types(&e.to_string()))))?;
    // A setting out of range was said as "sampler settings: samples = 0: must be 1 to 1024",
    // naming neither the transcript nor its config, though no flag of the user's gave it.
    if let Some(p) = config.problem() {
        return Err(bad(path, format!("\"config\": {p}")));
    }
    let scene = t["scene"]
        .as_str()
        .map(PathBuf::from)
        .ok_or_else(|| bad(path, "no \"scene\""))?;
    let mut exchanges = Vec::new();
    for (k, r) in t["records"]
        .as_array()
        .ok_or_else(|| bad(path, "no \"records\" list"))?
        .iter()
        .filter(|r| r["phase"] == "llm")
        .enumerate()
    {
        let d = &r["detail"];
        let refused = d["refused"].as_str().map(str::to_string);
        let reply = match (d["reply"].as_str(), &refused) {
            (Some(r), _) => r,
            (None, Some(_)) => "",
            (None, None) => return Err(bad(path, format!("exchange {k} has no reply"))),
        };
        let messages = serde_json::from_value(d["request"]["messages"].clone()).map_err(|e| {
            bad(
                path,
                format!(
                    "exchange {k}: its request's messages: {}",
                    plain_types(&e.to_string())
                ),
            )
        })?;
        exchanges.push(Exchange {
            messages,
            reply: reply.to_string(),
            refused,
            detail: d.clone(),
        });
    }
    if exchanges.is_empty() {
        return Err(bad(path, "it records no exchange with a server"));
    }
    let state = path.with_file_name("state.json");
    let checks = if state.is_file() {
        Some(
            serde_json::from_value(read_json(&state)?["checks"].clone()).map_err(|e| {
                bad(
                    &state,
                    format!("\"checks\": {}", plain_types(&e.to_string())),
                )
            })?,
        )
    } else {
        None
    };
    Ok(Recorded {
        path: path.to_path_buf(),
        scene,
        request: request.clone(),
        config,
        model: t["model"].as_str().map(str::to_string),
        checks,
        exchanges,
    })
}

/// Where two messages lists first differ, in words (`None` when they are the same).
pub fn first_difference(sent: &[Message], recorded: &[Message]) -> Option<String> {
    for (k, (a, b)) in sent.iter().zip(recorded).enumerate() {
        if a != b {
            let line = a
                .content
                .lines()
                .zip(b.content.lines())
                .position(|(x, y)| x != y)
                .map_or(String::new(), |l| format!(", line {}", l + 1));
            return Some(format!("message {k} ({}){line}", a.role));
        }
    }
    (sent.len() != recorded.len())
        .then(|| format!("{} messages sent, {} recorded", sent.len(), recorded.len()))
}

/// Where the run in `replayed` differs from the run in `original`: each round's script, each
/// sampling round's verdict (meets, achieved, passed, the reasons), and the outcome. Empty when
/// the replay reproduces the original.
pub fn compare(original: &Path, replayed: &Path) -> Result<Vec<String>, LlmError> {
    let mut out = Vec::new();
    let (a, b) = (
        read_json(&original.join("state.json"))?,
        read_json(&replayed.join("state.json"))?,
    );
    let rounds = |s: &Value| s["exchange"].as_u64().unwrap_or(0);
    // Up to the first round neither run holds: `exchange` is what the recording says, and
    // 10^15 of it looped for ever.
    let held = |n: &u64| {
        [original, replayed]
            .iter()
            .any(|d| d.join(format!("round_{n}")).is_dir())
    };
    for n in (0..rounds(&a).max(rounds(&b))).take_while(held) {
        // A regular file within the cap: a FIFO in a shared recording waited for ever.
        let script = |dir: &Path| {
            crate::io::read_regular_text(
                &dir.join(format!("round_{n}/script.rhai")),
                MAX_RUN_FILE_BYTES,
                "a round's script",
            )
            .ok()
        };
        if script(original) != script(replayed) {
            out.push(format!(
                "round {n}: the script differs (or only one run has one)"
            ));
        }
    }
    // The verdict as sampled; `success`, kept only since the one judgement of ask and the
    // batch table, is derived from it and absent from older recordings.
    let history = |s: &Value| {
        let mut h = s["history"].as_array().cloned().unwrap_or_default();
        for r in &mut h {
            if let Some(o) = r.as_object_mut() {
                o.remove("success");
            }
        }
        h
    };
    let (ha, hb) = (history(&a), history(&b));
    for (k, (x, y)) in ha.iter().zip(&hb).enumerate() {
        if x != y {
            out.push(format!(
                "sampling round {k}: the verdict differs: {x} recorded, {y} replayed"
            ));
        }
    }
    if ha.len() != hb.len() {
        out.push(format!(
            "{} sampling rounds recorded, {} replayed",
            ha.len(),
            hb.len()
        ));
    }
    if a["outcome"] != b["outcome"] {
        out.push(format!(
            "the outcome differs: {} recorded, {} replayed",
            a["outcome"], b["outcome"]
        ));
    }
    Ok(out)
}

/// What [`compare_replay`] found: the differences, and what it could not compare.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ReplayComparison {
    /// Where the replay differs (empty when it reproduces what was compared).
    pub differences: Vec<String>,
    /// What was left uncompared, in words (`None` when the whole run was compared).
    pub not_compared: Option<String>,
}

/// Compares the replay in `replayed` with the run recorded in `transcript`. With the run's
/// directory beside it (its state.json and rounds) the whole run is compared ([`compare`]).
/// A transcript moved or shared on its own holds the outcome alone: that is compared, and
/// what could not be is said. A replay of such a transcript compared nothing before and said
/// nothing, so a changed outcome passed as reproduced (exit 0).
pub fn compare_replay(transcript: &Path, replayed: &Path) -> Result<ReplayComparison, LlmError> {
    let original = transcript.parent().unwrap_or(Path::new("."));
    if original.join("state.json").is_file() {
        return Ok(ReplayComparison {
            differences: compare(original, replayed)?,
            not_compared: None,
        });
    }
    let t = read_json(transcript)?;
    let b = read_json(&replayed.join("state.json"))?;
    let mut differences = Vec::new();
    let why = format!(
        "{} has no state.json beside it (the transcript was moved from its run directory), so \
         the scripts and verdicts of its rounds could not be compared",
        transcript.display()
    );
    if t["outcome"].is_null() {
        return Ok(ReplayComparison {
            differences,
            not_compared: Some(format!(
                "nothing was compared: {why}, and it records no outcome"
            )),
        });
    }
    if t["outcome"] != b["outcome"] {
        differences.push(format!(
            "the outcome differs: {} recorded, {} replayed",
            t["outcome"], b["outcome"]
        ));
    }
    Ok(ReplayComparison {
        differences,
        not_compared: Some(format!("only the outcome was compared: {why}")),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_transcript_naming_a_key_twice_is_refused_not_read_as_its_last_copy() {
        // `{"backend": "http", ..., "backend": "manual"}` was read as its last copy.
        let dir = tempfile::tempdir().unwrap();
        let f = dir.path().join("transcript.json");
        std::fs::write(&f, r#"{"backend": "manual", "backend": "http"}"#).unwrap();
        let e = read_transcript(&f).err().expect("refused").to_string();
        assert!(
            e.contains("transcript.json") && e.contains("the key \"backend\" twice"),
            "{e}"
        );
    }

    #[test]
    fn a_recording_claiming_endless_rounds_or_holding_a_fifo_is_compared_at_once() {
        // 10^15 exchanges looped for ever; a FIFO as a round's script waited for a writer.
        let (a, b) = (tempfile::tempdir().unwrap(), tempfile::tempdir().unwrap());
        for (d, exchange) in [(&a, 1_000_000_000_000_000u64), (&b, 1)] {
            let state = serde_json::json!({"exchange": exchange, "outcome": "x"});
            std::fs::write(d.path().join("state.json"), state.to_string()).unwrap();
            std::fs::create_dir(d.path().join("round_0")).unwrap();
        }
        std::fs::write(b.path().join("round_0/script.rhai"), "term(\"x\", 0.0);").unwrap();
        let made = std::process::Command::new("mkfifo")
            .arg(a.path().join("round_0/script.rhai"))
            .status();
        assert!(made.is_ok_and(|s| s.success()), "mkfifo");
        let t0 = std::time::Instant::now();
        let d = compare(a.path(), b.path()).unwrap();
        assert!(t0.elapsed().as_secs() < 5, "{:?}", t0.elapsed());
        assert_eq!(d, ["round 0: the script differs (or only one run has one)"]);
    }

    #[test]
    fn a_damaged_config_is_said_in_words_not_rust_types() {
        // "\"config\": invalid value: integer `-1`, expected usize".
        let d = tempfile::tempdir().unwrap();
        let t = d.path().join("transcript.json");
        let v = serde_json::json!({
            "backend": "http", "requests": ["r"], "config": {"rounds": -1},
            "scene": "s", "records": []
        });
        std::fs::write(&t, v.to_string()).unwrap();
        let e = read_transcript(&t)
            .err()
            .expect("a damaged config")
            .to_string();
        assert!(
            e.contains(
                "\"config\": invalid value: integer `-1`, expected a whole number, 0 or more"
            ),
            "{e}"
        );
    }

    #[test]
    fn a_config_setting_out_of_range_names_the_transcript() {
        // "sampler settings: samples = 0: must be 1 to 1024", naming no file.
        let d = tempfile::tempdir().unwrap();
        let t = d.path().join("transcript.json");
        let v = serde_json::json!({
            "backend": "http", "requests": ["r"], "scene": "s", "records": [],
            "config": {"context": null, "fixes": 3, "guidance": "output", "lambda": 3.0,
                       "max_agents": 30, "polish": 300,
                       "prompt": {"cot": "designed", "frenet": true}, "realism": 1.0,
                       "replan": null, "rounds": 1, "samples": 0, "script_budget": 300.0,
                       "seed": 1, "tolerance": 0.05}
        });
        std::fs::write(&t, v.to_string()).unwrap();
        let e = read_transcript(&t).err().expect("samples 0").to_string();
        assert!(
            e.contains("transcript.json") && e.contains("\"config\": samples = 0: must be 1 to"),
            "{e}"
        );
    }

    #[test]
    fn a_changed_prompt_is_located() {
        let a = [Message::new("system", "x"), Message::new("user", "a\nb")];
        let b = [Message::new("system", "x"), Message::new("user", "a\nc")];
        assert_eq!(first_difference(&a, &a), None);
        assert_eq!(
            first_difference(&a, &b).as_deref(),
            Some("message 1 (user), line 2")
        );
        assert_eq!(
            first_difference(&a[..1], &b).as_deref(),
            Some("1 messages sent, 2 recorded")
        );
    }
}
