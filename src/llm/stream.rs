//! A streamed chat completion (`"stream": true`): server-sent events, one `data:` line per
//! chunk of the reply, read as they come so that a slow model shows signs of life and a
//! stream that stops is told apart from one that is merely slow.
//!
//! The silence limit is the client's read timeout, applied to each read: a local model may
//! think for minutes before its first token and then write for minutes more, and neither is
//! an error; nothing arriving for that long is, and so is a stream that brings no token for
//! that long however many keep-alive comments or empty chunks it sends ([`ReplyClock`]).
//! Reasoning tokens (`reasoning_content`, `reasoning`) are progress too, though not part of
//! the reply.

use std::io::{BufRead, BufReader, Read};
use std::time::{Duration, Instant};

use serde_json::Value;

use super::client::{error_message_redacted, Usage, MAX_REPLY_BYTES};
use super::clock::{abandoned, Abandoned, ReplyClock};
use super::LlmError;

/// A stream read to its end.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Streamed {
    /// The reply's text, every chunk's content in order.
    pub content: String,
    /// The usage the last chunk reported, where the server sends one.
    pub usage: Option<Usage>,
    /// The server stopped the reply at the token limit.
    pub truncated: bool,
    /// Chunks with content (one token each on every server seen).
    pub tokens: usize,
    /// Chunks with reasoning only (`reasoning_content`, `reasoning`: a thinking model's
    /// thoughts, which are not part of the reply).
    pub reasoning: usize,
    /// The chunks' `system_fingerprint` (Ollama's is `fp_ollama`).
    pub fingerprint: Option<String>,
}

/// One line for a terminal: tokens so far, their rate since the first, and the time since the
/// request was sent.
pub fn progress_line(tokens: usize, since_first: Option<Duration>, elapsed: Duration) -> String {
    let rate = match since_first {
        Some(d) if d.as_secs_f64() > 0.0 && tokens > 1 => {
            format!("{:.1} tokens/s", (tokens - 1) as f64 / d.as_secs_f64())
        }
        _ => "- tokens/s".into(),
    };
    format!(
        "{tokens} tokens, {rate}, {:.0} s elapsed",
        elapsed.as_secs_f64()
    )
}

/// What a stream brought, in words: its tokens, and its reasoning tokens where it had any.
fn received(s: &Streamed) -> String {
    match s.reasoning {
        0 => format!("{} tokens", s.tokens),
        r => format!("{} tokens and {r} reasoning tokens", s.tokens),
    }
}

/// Whether a reply body is a stream of events: by its type, or by its first bytes where a
/// server labels it wrongly.
pub fn is_event_stream(content_type: Option<&str>, head: &[u8]) -> bool {
    let head = String::from_utf8_lossy(head);
    let head = head.trim_start_matches('\u{feff}').trim_start();
    // A JSON body labelled as a stream (a proxy's or a server's mislabel) was read as events:
    // it held none, and the reply was called "ended after 0 tokens", as if the server died.
    if head.starts_with('{') {
        return false;
    }
    if content_type.is_some_and(|t| t.to_ascii_lowercase().contains("text/event-stream")) {
        return true;
    }
    head.starts_with("data:") || head.starts_with("event:") || head.starts_with(": ")
}

/// The text of a message's `content`: a string, or an array of parts whose `text` fields
/// are joined (some servers send content parts, streamed too); anything else is none.
pub(crate) fn content_text(v: &Value) -> Option<String> {
    match v {
        Value::String(s) => Some(s.clone()),
        Value::Array(parts) => Some(
            parts
                .iter()
                .filter(|p| p["type"].as_str().is_none_or(|t| t == "text"))
                .filter_map(|p| p["text"].as_str())
                .collect::<Vec<_>>()
                .join(""),
        ),
        _ => None,
    }
}

/// The refusal a message carries (`refusal`, or content parts of type `refusal`), if any.
pub(crate) fn refusal_text(message: &Value) -> String {
    let mut out = message["refusal"].as_str().unwrap_or("").to_string();
    if let Some(parts) = message["content"].as_array() {
        for p in parts.iter().filter(|p| p["type"] == "refusal") {
            out.push_str(p["refusal"].as_str().unwrap_or(""));
        }
    }
    out
}

/// The names of the tools a message calls (`tool_calls`, or the older `function_call`), as
/// sent, each once.
pub(crate) fn tool_names(message: &Value, into: &mut Vec<String>) {
    let calls = message["tool_calls"].as_array().into_iter().flatten();
    let names = calls
        .map(|c| &c["function"]["name"])
        .chain(std::iter::once(&message["function_call"]["name"]));
    for n in names.filter_map(Value::as_str).filter(|n| !n.is_empty()) {
        if !into.iter().any(|x| x == n) {
            into.push(n.to_string());
        }
    }
}

/// Why a reply with no text cannot be used, where the model said why: it refused (its
/// words, cut to 300 characters: [`LlmError::Refused`]), or it called a tool drivescript
/// never offered (an unusable reply). `None` where it did neither (an empty reply, which goes
/// back to the model as such). What the server sent is `redact`ed before it is cut, so that
/// no part of a key it echoed is left.
pub(crate) fn no_text_error(
    url: &str,
    refusal: &str,
    tools: &[String],
    tool_finish: bool,
    redact: &dyn Fn(&str) -> String,
) -> Option<LlmError> {
    let reason = no_text_reason(refusal, tools, tool_finish, redact)?;
    Some(if refusal.trim().is_empty() {
        LlmError::BadReply {
            url: url.into(),
            message: reason,
        }
    } else {
        LlmError::Refused {
            url: url.into(),
            message: reason,
        }
    })
}

fn no_text_reason(
    refusal: &str,
    tools: &[String],
    tool_finish: bool,
    redact: &dyn Fn(&str) -> String,
) -> Option<String> {
    let refusal = redact(refusal.trim());
    let refusal = refusal.trim();
    if !refusal.is_empty() {
        let mut shown: String = refusal.chars().take(300).collect();
        if refusal.chars().count() > 300 {
            shown.push_str("...");
        }
        return Some(format!(
            "the model refused to answer: \"{}\"; asking again gets the same answer: reword \
             the request, or use another model",
            crate::io::name::terminal_safe(&shown.replace(['\n', '\r'], " "))
        ));
    }
    if !tools.is_empty() || tool_finish {
        let names: Vec<String> = tools
            .iter()
            .map(|t| crate::io::name::shown_counted(&redact(t)))
            .collect();
        let which = match names.len() {
            0 => "a tool".to_string(),
            _ => format!("the tool {}", crate::io::name::first_few(&names, 3)),
        };
        return Some(format!(
            "the model answered with a call of {which} and no text: drivescript offers it no \
             tools, so a proxy or the server's chat template adds them; turn that off, or use \
             another model"
        ));
    }
    None
}

/// Reads one line of an event stream into `line`, its end included: the format ends lines
/// with LF, CRLF or a bare CR, and a server ending them with CR alone (the format allows it)
/// had its whole stream read as one line, which never ended. `after_cr` carries a CR that
/// ended the last line, so that the LF of a CRLF split across reads is not taken for an empty
/// line (which would end an event early). Returns the bytes taken from the reader.
fn read_event_line<R: BufRead>(
    reader: &mut R,
    line: &mut Vec<u8>,
    after_cr: &mut bool,
) -> std::io::Result<usize> {
    let mut taken = 0;
    loop {
        let buf = match reader.fill_buf() {
            Ok(b) => b,
            Err(e) if e.kind() == std::io::ErrorKind::Interrupted => continue,
            Err(e) => return Err(e),
        };
        if buf.is_empty() {
            return Ok(taken);
        }
        let mut start = 0;
        if std::mem::take(after_cr) && buf[0] == b'\n' {
            start = 1;
        }
        match buf[start..].iter().position(|&b| b == b'\n' || b == b'\r') {
            Some(i) => {
                let end = start + i;
                line.extend_from_slice(&buf[start..=end]);
                *after_cr = buf[end] == b'\r';
                reader.consume(end + 1);
                return Ok(taken + end + 1);
            }
            None => {
                line.extend_from_slice(&buf[start..]);
                let n = buf.len();
                reader.consume(n);
                taken += n;
            }
        }
    }
}

/// The `index` of a choice: absent (or null) is 0, as servers asked for one answer leave it;
/// anything but a whole number from 0 is refused, quoted through `redact`: `-1`, `"0"` and
/// `1.0` were each taken for index 0, and their text for the answer.
fn choice_index(c: &Value, redact: &dyn Fn(&str) -> String) -> Result<u64, String> {
    match c.get("index") {
        None | Some(Value::Null) => Ok(0),
        Some(v) => v.as_u64().ok_or_else(|| {
            format!(
                "choice has \"index\" {}, not a whole number from 0",
                redact(&crate::io::name::shown_counted(&v.to_string()))
            )
        }),
    }
}

/// The choice of index 0 among `choices` (a reply's, or a stream event's), the answer asked
/// for; `None` where there is none. Two of index 0 are refused: which is the answer is
/// unclear (the first listed was taken). The message starts with what it is about, to follow
/// "the reply's" or "a stream event's".
pub(super) fn answer_choice<'v>(
    choices: Option<&'v Vec<Value>>,
    redact: &dyn Fn(&str) -> String,
) -> Result<Option<&'v Value>, String> {
    let mut answer = None;
    for c in choices.into_iter().flatten() {
        if choice_index(c, redact)? == 0 {
            if answer.is_some() {
                return Err(
                    "\"choices\" hold two choices of index 0, so which one is the \
                            answer is unclear"
                        .into(),
                );
            }
            answer = Some(c);
        }
    }
    Ok(answer)
}

/// What a stream has brought so far, and how its reply ends.
#[derive(Default)]
struct Reading {
    out: Streamed,
    first: Option<Instant>,
    finished: bool,
    refusal: String,
    tools: Vec<String>,
    tool_finish: bool,
    got: usize,
}

impl Reading {
    /// Takes one event's data (its `data:` lines joined), with its JSON where the caller has
    /// parsed it already: `Ok(true)` where it is `[DONE]`.
    #[allow(clippy::too_many_arguments)]
    fn event(
        &mut self,
        data: &str,
        parsed: Option<Value>,
        event: &str,
        url: &str,
        clock: &ReplyClock,
        redact: &dyn Fn(&str) -> String,
        tick: &mut dyn FnMut(usize, Option<Duration>),
    ) -> Result<bool, LlmError> {
        let bad = |message: String| LlmError::BadReply {
            url: url.into(),
            message,
        };
        let out = &mut self.out;
        if event.eq_ignore_ascii_case("error") {
            return Err(bad(format!(
                "the server sent an error event after {} tokens: {}",
                out.tokens,
                error_message_redacted(data, redact)
            )));
        }
        if data == "[DONE]" {
            return Ok(true);
        }
        let v: Value = match parsed {
            Some(v) => v,
            None => crate::io::json::parse_json(data).map_err(|e| {
                // Redacted whole, then cut: cut first, a key echoed across the cut kept its head.
                let head: String = redact(data).chars().take(120).collect();
                bad(if e.is_data() {
                    format!("a stream event holds {e}, so what it says is unclear: {head:?}")
                } else {
                    format!("a stream event is not JSON ({e}): {head:?}")
                })
            })?,
        };
        if v.get("error").is_some_and(|e| !e.is_null()) {
            return Err(bad(format!(
                "the server sent an error in the middle of the stream, after {} tokens: {}",
                out.tokens,
                error_message_redacted(data, redact)
            )));
        }
        if let Some(f) = v["system_fingerprint"].as_str() {
            out.fingerprint = Some(f.to_string());
        }
        if let Some(u) = v
            .get("usage")
            .and_then(|u| serde_json::from_value::<Usage>(u.clone()).ok())
        {
            out.usage = Some(u);
        }
        // The first choice is the one of index 0 (a choice with none is taken for it): a
        // chunk of another choice (a gateway asking for several) was appended to the reply.
        let Some(choice) = answer_choice(v["choices"].as_array(), redact)
            .map_err(|m| bad(format!("a stream event's {m}")))?
        else {
            return Ok(false);
        };
        let delta = &choice["delta"];
        // Content parts (an array of `{type: "text", text}`) were dropped, and the reply
        // called empty.
        let piece = content_text(&delta["content"])
            .or_else(|| choice["text"].as_str().map(str::to_string))
            .unwrap_or_default();
        let piece = piece.as_str();
        // A refusal or a tool call brings no content: the reply was called empty and asked
        // for again, up to --fixes times, each answered alike.
        self.refusal.push_str(&refusal_text(delta));
        tool_names(delta, &mut self.tools);
        let thought = ["reasoning_content", "reasoning"]
            .iter()
            .any(|k| choice["delta"][k].as_str().is_some_and(|t| !t.is_empty()));
        if !piece.is_empty() {
            out.content.push_str(piece);
            out.tokens += 1;
        } else if thought {
            out.reasoning += 1;
        }
        if !piece.is_empty() || thought {
            clock.token();
            let t = *self.first.get_or_insert_with(Instant::now);
            tick(out.tokens + out.reasoning, Some(t.elapsed()));
        }
        if let Some(reason) = choice["finish_reason"].as_str() {
            if reason == "content_filter" {
                return Err(bad(super::client::content_filtered(
                    out.content.chars().count(),
                )));
            }
            // vLLM ends a request it stopped itself (the client went, the server shuts down)
            // with "abort"; the part that came was taken for the model's whole reply.
            if ["abort", "aborted", "error", "cancelled", "canceled"].contains(&reason) {
                return Err(LlmError::Reset {
                    url: url.into(),
                    bytes: self.got,
                    message: format!(
                        "the server stopped the reply itself (finish_reason \"{reason}\") after \
                         {} tokens",
                        out.tokens
                    ),
                });
            }
            self.tool_finish |= reason == "tool_calls" || reason == "function_call";
            self.finished = true;
            out.truncated |= reason == "length";
        }
        Ok(false)
    }
}

/// The JSON of the data gathered for an event, where it is whole. An event's JSON may come
/// over several `data:` lines (the format joins them), and some servers end no event with a
/// blank line, so an event is taken as soon as its data parses, without waiting for the blank
/// line that may never come.
fn whole(data: &str) -> Option<Value> {
    crate::io::json::parse_json(data).ok()
}

/// Reads the events of `body` until `data: [DONE]`, a chunk with a `finish_reason` followed
/// by the end of the body, or an error. `tick(tokens, since_first_token)` is called after
/// each chunk with content or reasoning. `read_error` turns a failed read into the client's
/// error, given the bytes read; a read that times out, or a stream that brings no token for
/// the clock's progress limit, is a stalled stream, and one still coming at the clock's
/// deadline is abandoned ([`LlmError::Deadline`]). `redact` takes the client's secrets out of
/// what the server sent before any of it is quoted, cut, in an error.
pub fn read_stream<R: Read>(
    body: R,
    url: &str,
    clock: &ReplyClock,
    read_error: &dyn Fn(&std::io::Error, usize) -> LlmError,
    redact: &dyn Fn(&str) -> String,
    tick: &mut dyn FnMut(usize, Option<Duration>),
) -> Result<Streamed, LlmError> {
    let bad = |message: String| LlmError::BadReply {
        url: url.into(),
        message,
    };
    clock.restart_progress();
    let mut reader = BufReader::new(clock.reader(body, true).take(MAX_REPLY_BYTES + 1));
    let mut r = Reading::default();
    let mut event = String::new();
    // The data of the event being read: its `data:` lines, joined by newlines.
    let mut data = String::new();
    let mut line = Vec::new();
    let mut after_cr = false;
    loop {
        line.clear();
        let n = match read_event_line(&mut reader, &mut line, &mut after_cr) {
            Ok(n) => n,
            Err(e) => {
                let out = &r.out;
                let stalled = |keepalive| LlmError::Stalled {
                    url: url.into(),
                    seconds: clock.progress().as_secs_f64(),
                    tokens: out.tokens,
                    keepalive,
                };
                return Err(match abandoned(&e) {
                    Some(Abandoned::Deadline) => clock.past_deadline(url, &received(out)),
                    Some(Abandoned::NoProgress) => stalled(true),
                    None => match read_error(&e, r.got) {
                        LlmError::Deadline { .. } => clock.past_deadline(url, &received(out)),
                        LlmError::Timeout { .. } => stalled(false),
                        other => other,
                    },
                });
            }
        };
        let first_line = r.got == 0;
        r.got += n;
        if r.got as u64 > MAX_REPLY_BYTES {
            return Err(bad(format!(
                "the streamed reply is larger than {} MB: no completion is; the server is \
                 broken or not an LLM server",
                MAX_REPLY_BYTES >> 20
            )));
        }
        // The end of the body, or a blank line, ends an event whatever its data holds; data
        // that did not parse then is no JSON, and is said to be.
        let text = String::from_utf8_lossy(&line);
        // A byte order mark may begin a stream (the event-stream format ignores it): the
        // first event, the whole reply from some servers, was skipped as a line of no field.
        let text = if first_line {
            text.trim_start_matches('\u{feff}')
        } else {
            text.as_ref()
        };
        let text = text.trim();
        if n == 0 || text.is_empty() {
            if !data.is_empty() && r.event(&data, None, &event, url, clock, redact, tick)? {
                break;
            }
            data.clear();
            event.clear();
        }
        if n == 0 {
            if r.finished {
                break;
            }
            // The body ended without the reply's end: the server went away mid-reply.
            return Err(LlmError::Reset {
                url: url.into(),
                bytes: r.got,
                message: format!(
                    "the event stream ended after {} tokens without a finish_reason or [DONE]",
                    r.out.tokens
                ),
            });
        }
        // `:` lines are keep-alive comments; `id:` and `retry:` carry nothing a completion
        // needs. `event: error` names an event that carries the server's error in a shape of
        // its own (`{"message": ...}`): it was read as a chunk of no choices and the stream
        // called "ended after 0 tokens", the message dropped.
        if let Some(name) = text.strip_prefix("event:") {
            event = name.trim().to_string();
        }
        let Some(more) = text.strip_prefix("data:") else {
            continue;
        };
        // JSON is UTF-8: bytes that are not were stored as U+FFFD in the reply without a word.
        if let Err(e) = std::str::from_utf8(&line) {
            return Err(bad(format!(
                "a stream event is not UTF-8 (byte {} of the event, after {} tokens), as JSON \
                 must be: the server is broken or sends another encoding",
                e.valid_up_to() + 1,
                r.out.tokens
            )));
        }
        let more = more.trim();
        // Data that never parsed, then `[DONE]` with no blank line between (a server that
        // ends no event with one): the data is said to be no JSON, rather than the reply
        // stalling on it for want of a token.
        if more == "[DONE]" && !data.is_empty() {
            r.event(&data, None, &event, url, clock, redact, tick)?;
            data.clear();
        }
        if !data.is_empty() {
            data.push('\n');
        }
        data.push_str(more);
        // An error event's plain-text message is taken at once: the server may keep the
        // stream open after it.
        let error_text = event.eq_ignore_ascii_case("error") && !data.starts_with(['{', '[']);
        let parsed = whole(&data);
        if data == "[DONE]" || parsed.is_some() || error_text {
            let done = r.event(&data, parsed, &event, url, clock, redact, tick)?;
            data.clear();
            event.clear();
            if done {
                break;
            }
        }
    }
    let Reading {
        out,
        refusal,
        tools,
        tool_finish,
        ..
    } = r;
    if out.content.trim().is_empty() {
        if let Some(e) = no_text_error(url, &refusal, &tools, tool_finish, redact) {
            return Err(e);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn no_read_error(_: &std::io::Error, _: usize) -> LlmError {
        LlmError::Setup("unexpected".into())
    }

    fn clock(deadline_ms: u64, progress_ms: u64) -> ReplyClock {
        ReplyClock::new(
            Instant::now(),
            Duration::from_millis(deadline_ms),
            Duration::from_millis(progress_ms),
        )
    }

    fn read(body: &str) -> Result<Streamed, LlmError> {
        read_stream(
            body.as_bytes(),
            "u",
            &clock(60_000, 1000),
            &no_read_error,
            &|s| s.to_string(),
            &mut |_, _| {},
        )
    }

    /// A server that sends `first`, then `then` for ever, one line per read, `gap` apart.
    struct Endless {
        first: Vec<String>,
        then: String,
        gap: Duration,
    }

    impl Read for Endless {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            std::thread::sleep(self.gap);
            let line = if self.first.is_empty() {
                self.then.clone()
            } else {
                self.first.remove(0)
            };
            let b = format!("{line}\n\n").into_bytes();
            buf[..b.len()].copy_from_slice(&b);
            Ok(b.len())
        }
    }

    fn endless(then: &str, clock: &ReplyClock) -> (LlmError, Duration) {
        let body = Endless {
            first: vec!["data: {\"choices\":[{\"delta\":{\"content\":\"x\"}}]}".into()],
            then: then.into(),
            gap: Duration::from_millis(10),
        };
        let t0 = Instant::now();
        let e = read_stream(
            body,
            "u",
            clock,
            &no_read_error,
            &|s| s.to_string(),
            &mut |_, _| {},
        )
        .unwrap_err();
        (e, t0.elapsed())
    }

    #[test]
    fn keep_alives_and_empty_chunks_for_ever_are_a_stall_and_tokens_for_ever_hit_the_deadline() {
        for then in [": ping", "data: {\"choices\":[{\"delta\":{}}]}"] {
            let (e, took) = endless(then, &clock(60_000, 200));
            assert!(
                matches!(
                    e,
                    LlmError::Stalled {
                        tokens: 1,
                        keepalive: true,
                        ..
                    }
                ),
                "{then}: {e:?}"
            );
            assert!(e.to_string().contains("no token came"), "{e}");
            assert!(took < Duration::from_secs(3), "{then}: {took:?}");
        }
        // Thinking is progress: a model that reasons for ever is held by the deadline only.
        let thinking = "data: {\"choices\":[{\"delta\":{\"reasoning_content\":\"hm\"}}]}";
        let (e, took) = endless(thinking, &clock(600, 200));
        assert!(matches!(e, LlmError::Deadline { .. }), "{e:?}");
        assert!(took >= Duration::from_millis(600), "{took:?}");
        let e = e.to_string();
        assert!(
            e.contains("past the reply deadline of 0.6 s")
                && e.contains("with 1 tokens and ")
                && e.contains(" reasoning tokens received")
                && e.contains("--reply-deadline"),
            "{e}"
        );
        let token = "data: {\"choices\":[{\"delta\":{\"content\":\"y\"}}]}";
        let (e, took) = endless(token, &clock(300, 200));
        assert!(matches!(e, LlmError::Deadline { .. }), "{e:?}");
        assert!(took < Duration::from_secs(3), "{took:?}");
    }

    #[test]
    fn chunks_join_into_the_reply_with_usage_and_the_token_limit() {
        let body = ": keep-alive\n\n\
            data: {\"choices\":[{\"delta\":{\"role\":\"assistant\"}}]}\n\n\
            data: {\"choices\":[{\"delta\":{\"content\":\"AC\"}}]}\n\n\
            data: {\"choices\":[{\"delta\":{\"content\":\"CEPT\"},\"finish_reason\":\"length\"}]}\n\n\
            data: {\"choices\":[],\"usage\":{\"prompt_tokens\":7,\"completion_tokens\":2}}\n\n\
            data: [DONE]\n\n";
        let s = read(body).unwrap();
        assert_eq!(s.content, "ACCEPT");
        assert_eq!(s.tokens, 2);
        assert!(s.truncated);
        assert_eq!(
            s.usage,
            Some(Usage {
                prompt_tokens: 7,
                completion_tokens: 2
            })
        );
        // Without [DONE], a finish_reason and the end of the body end it too.
        let s = read(
            "data: {\"choices\":[{\"delta\":{\"content\":\"x\"},\"finish_reason\":\"stop\"}]}\n",
        )
        .unwrap();
        assert_eq!((s.content.as_str(), s.truncated), ("x", false));
    }

    #[test]
    fn a_stream_cut_off_an_error_event_or_garbage_says_which() {
        let e = read("data: {\"choices\":[{\"delta\":{\"content\":\"x\"}}]}\n").unwrap_err();
        assert!(
            matches!(e, LlmError::Reset { .. }) && e.to_string().contains("after 1 tokens"),
            "{e}"
        );
        let e = read("data: {\"error\":{\"message\":\"out of memory\"}}\n").unwrap_err();
        assert!(e.to_string().contains("out of memory"), "{e}");
        let e = read("data: <html>\n").unwrap_err();
        assert!(e.to_string().contains("not JSON"), "{e}");
        // A chunk of index -1 or "0" was appended to the answer as index 0's.
        for index in ["-1", "\"0\""] {
            let e = read(&format!(
                "data: {{\"choices\":[{{\"index\":{index},\"delta\":{{\"content\":\"x\"}}}}]}}\n"
            ))
            .unwrap_err()
            .to_string();
            assert!(
                e.contains(&format!(
                    "a stream event's choice has \"index\" {index}, not a whole number from 0"
                )),
                "{e}"
            );
        }
        let e = read(
            "data: {\"choices\":[{\"delta\":{\"content\":\"x\"}},{\"index\":0,\"delta\":{\"content\":\"y\"}}]}\n",
        )
        .unwrap_err();
        assert!(e.to_string().contains("two choices of index 0"), "{e}");
    }

    /// A body that gives one byte per read, so that every line end is split across reads.
    struct Trickle<'a>(&'a [u8]);

    impl Read for Trickle<'_> {
        fn read(&mut self, buf: &mut [u8]) -> std::io::Result<usize> {
            let Some((&b, rest)) = self.0.split_first() else {
                return Ok(0);
            };
            buf[0] = b;
            self.0 = rest;
            Ok(1)
        }
    }

    #[test]
    fn an_event_over_several_data_lines_and_any_line_end_are_read() {
        // The format joins an event's `data:` lines and ends lines with LF, CRLF or CR: an
        // event split over lines was refused as "not JSON", and a stream of bare CRs was one
        // line that never ended (issue 32).
        let lf = "data: {\"choices\":[{\"delta\":\n\
                  data: {\"content\":\"AC\"}}]}\n\n\
                  : keep-alive\n\n\
                  data: {\"choices\":[{\"delta\":{\"content\":\"CEPT\"},\n\
                  data:  \"finish_reason\":\"stop\"}]}\n\n\
                  data: [DONE]\n\n";
        for body in [
            lf.to_string(),
            lf.replace('\n', "\r\n"),
            lf.replace('\n', "\r"),
        ] {
            for trickle in [false, true] {
                let got = if trickle {
                    read_stream(
                        Trickle(body.as_bytes()),
                        "u",
                        &clock(60_000, 1000),
                        &no_read_error,
                        &|s| s.to_string(),
                        &mut |_, _| {},
                    )
                } else {
                    read(&body)
                };
                let s = got.unwrap_or_else(|e| panic!("{body:?}: {e}"));
                assert_eq!((s.content.as_str(), s.tokens), ("ACCEPT", 2), "{body:?}");
            }
        }
        // Servers that end no event with a blank line still work, one event per line.
        let s = read(
            "data: {\"choices\":[{\"delta\":{\"content\":\"a\"}}]}\r\
             data: {\"choices\":[{\"delta\":{\"content\":\"b\"},\"finish_reason\":\"stop\"}]}\r\
             data: [DONE]\r",
        )
        .unwrap();
        assert_eq!((s.content.as_str(), s.tokens), ("ab", 2));
        // Data that never parses is said to be no JSON at a blank line, at [DONE] and at the
        // end of the body, never waited on.
        for body in [
            "data: {\"choices\":\n\ndata: [DONE]\n\n",
            "data: {\"choices\":\ndata: [DONE]\n",
            "data: {\"choices\":\n",
        ] {
            let e = read(body).unwrap_err().to_string();
            assert!(
                e.contains("not JSON") && e.contains("choices"),
                "{body:?}: {e}"
            );
        }
        // An error event's JSON over two lines is read whole.
        let e = read("event: error\ndata: {\"message\":\ndata: \"out of memory\"}\n\n")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("error event") && e.contains("out of memory"),
            "{e}"
        );
    }

    #[test]
    fn streams_are_recognised_by_type_or_by_their_first_bytes() {
        assert!(is_event_stream(
            Some("text/event-stream; charset=utf-8"),
            b""
        ));
        assert!(is_event_stream(Some("application/json"), b"\ndata: {}"));
        assert!(!is_event_stream(
            Some("application/json"),
            b"{\"choices\":[]}"
        ));
    }

    #[test]
    fn the_progress_line_gives_tokens_rate_and_elapsed_time() {
        assert_eq!(
            progress_line(11, Some(Duration::from_secs(2)), Duration::from_secs(30)),
            "11 tokens, 5.0 tokens/s, 30 s elapsed"
        );
        assert_eq!(
            progress_line(1, Some(Duration::ZERO), Duration::from_secs(3)),
            "1 tokens, - tokens/s, 3 s elapsed"
        );
    }
}
