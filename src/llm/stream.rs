//! A streamed chat completion (`"stream": true`): server-sent events, one `data:` line per
//! chunk of the reply, read as they come so that a slow model shows signs of life and a
//! stream that stops is told apart from one that is merely slow.
//!
//! The silence limit is the client's read timeout, applied to each read: a local model may
//! think for minutes before its first token and then write for minutes more, and neither is
//! an error; nothing arriving for that long is.

use std::io::{BufRead, BufReader, Read};
use std::time::{Duration, Instant};

use serde_json::Value;

use super::client::{error_message, Usage, MAX_REPLY_BYTES};
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

/// Whether a reply body is a stream of events: by its type, or by its first bytes where a
/// server labels it wrongly.
pub fn is_event_stream(content_type: Option<&str>, head: &[u8]) -> bool {
    if content_type.is_some_and(|t| t.to_ascii_lowercase().contains("text/event-stream")) {
        return true;
    }
    let head = String::from_utf8_lossy(head);
    let head = head.trim_start();
    head.starts_with("data:") || head.starts_with("event:") || head.starts_with(": ")
}

/// Reads the events of `body` until `data: [DONE]`, a chunk with a `finish_reason` followed
/// by the end of the body, or an error. `tick(tokens, since_first_token)` is called after
/// each chunk with content. `read_error` turns a failed read into the client's error, given
/// the bytes read; a read that times out is a stalled stream.
pub fn read_stream<R: Read>(
    body: R,
    url: &str,
    silence: Duration,
    read_error: &dyn Fn(&std::io::Error, usize) -> LlmError,
    tick: &mut dyn FnMut(usize, Option<Duration>),
) -> Result<Streamed, LlmError> {
    let bad = |message: String| LlmError::BadReply {
        url: url.into(),
        message,
    };
    let mut reader = BufReader::new(body.take(MAX_REPLY_BYTES + 1));
    let mut out = Streamed::default();
    let mut first: Option<Instant> = None;
    let mut finished = false;
    let mut got = 0usize;
    let mut line = Vec::new();
    loop {
        line.clear();
        let n = match reader.read_until(b'\n', &mut line) {
            Ok(n) => n,
            Err(e) => {
                return Err(match read_error(&e, got) {
                    LlmError::Timeout { .. } => LlmError::Stalled {
                        url: url.into(),
                        seconds: silence.as_secs_f64(),
                        tokens: out.tokens,
                    },
                    other => other,
                })
            }
        };
        got += n;
        if got as u64 > MAX_REPLY_BYTES {
            return Err(bad(format!(
                "the streamed reply is larger than {} MB: no completion is; the server is \
                 broken or not an LLM server",
                MAX_REPLY_BYTES >> 20
            )));
        }
        if n == 0 {
            if finished {
                break;
            }
            // The body ended without the reply's end: the server went away mid-reply.
            return Err(LlmError::Reset {
                url: url.into(),
                bytes: got,
                message: format!(
                    "the event stream ended after {} tokens without a finish_reason or [DONE]",
                    out.tokens
                ),
            });
        }
        let text = String::from_utf8_lossy(&line);
        let text = text.trim();
        // Blank lines end events; `:` lines are keep-alive comments; `event:`, `id:` and
        // `retry:` carry nothing a completion needs.
        let Some(data) = text.strip_prefix("data:") else {
            continue;
        };
        let data = data.trim();
        if data == "[DONE]" {
            break;
        }
        let v: Value = serde_json::from_str(data).map_err(|e| {
            let head: String = data.chars().take(120).collect();
            bad(format!("a stream event is not JSON ({e}): {head:?}"))
        })?;
        if v.get("error").is_some_and(|e| !e.is_null()) {
            return Err(bad(format!(
                "the server sent an error in the middle of the stream, after {} tokens: {}",
                out.tokens,
                error_message(data)
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
        let Some(choice) = v["choices"].as_array().and_then(|c| c.first()) else {
            continue;
        };
        let piece = choice["delta"]["content"]
            .as_str()
            .or_else(|| choice["text"].as_str())
            .unwrap_or("");
        if !piece.is_empty() {
            out.content.push_str(piece);
            out.tokens += 1;
            let t = *first.get_or_insert_with(Instant::now);
            tick(out.tokens, Some(t.elapsed()));
        }
        if let Some(reason) = choice["finish_reason"].as_str() {
            finished = true;
            out.truncated |= reason == "length";
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

    fn read(body: &str) -> Result<Streamed, LlmError> {
        read_stream(
            body.as_bytes(),
            "u",
            Duration::from_secs(1),
            &no_read_error,
            &mut |_, _| {},
        )
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
