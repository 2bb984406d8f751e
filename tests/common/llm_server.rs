//! A real HTTP/1.1 server on 127.0.0.1 with scripted replies, standing in for an
//! OpenAI-compatible LLM server. One reply per request, in order; every request is recorded.

use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpListener;
use std::sync::{Arc, Mutex};
use std::time::Duration;

/// In a canned body, replaced by [`prompt_tokens`] of the request answered.
pub const PROMPT_TOKENS: &str = "__prompt_tokens__";

/// The tokens of a request's messages as a tokenizer of 4 characters per token counts them:
/// what a server that read the whole prompt reports.
pub fn prompt_tokens(request_body: &str) -> u64 {
    let v: serde_json::Value = serde_json::from_str(request_body).unwrap_or_default();
    let chars: usize = v["messages"]
        .as_array()
        .map(|m| {
            m.iter()
                .map(|m| m["content"].as_str().unwrap_or("").chars().count())
                .sum()
        })
        .unwrap_or(0);
    (chars / 4) as u64
}

/// One scripted reply.
#[derive(Clone)]
pub struct Canned {
    pub status: u16,
    pub headers: Vec<(String, String)>,
    pub body: String,
    /// Wait before answering (read timeouts).
    pub delay: Duration,
    /// Server-sent events instead of `body`: each `data:` payload, written `gap` apart.
    pub events: Option<(Vec<String>, Duration)>,
}

impl Canned {
    /// A chat completion whose first choice says `content`, reporting the prompt's tokens as
    /// [`prompt_tokens`] counts them (a server that read the whole prompt).
    pub fn chat(content: &str) -> Self {
        let body = serde_json::json!({
            "id": "chatcmpl-test",
            "object": "chat.completion",
            "choices": [{"index": 0, "message": {"role": "assistant", "content": content}, "finish_reason": "stop"}],
            "usage": {"prompt_tokens": PROMPT_TOKENS, "completion_tokens": 200}
        });
        Self::raw(200, &body.to_string())
    }

    /// Any status and body.
    pub fn raw(status: u16, body: &str) -> Self {
        Self {
            status,
            headers: Vec::new(),
            body: body.into(),
            delay: Duration::ZERO,
            events: None,
        }
    }

    /// A streamed chat completion of `content`, a word per event, `gap` apart, with usage and
    /// `[DONE]` at the end.
    pub fn stream(content: &str, gap: Duration) -> Self {
        let mut events: Vec<String> = content
            .split_inclusive(' ')
            .map(|w| {
                serde_json::json!({"choices": [{"index": 0, "delta": {"content": w}}]}).to_string()
            })
            .collect();
        events.push(
            serde_json::json!({"choices": [{"index": 0, "delta": {}, "finish_reason": "stop"}]})
                .to_string(),
        );
        events.push(
            serde_json::json!({"choices": [], "usage": {"prompt_tokens": PROMPT_TOKENS, "completion_tokens": 200}})
                .to_string(),
        );
        events.push("[DONE]".into());
        Self::events(events, gap)
    }

    /// These `data:` payloads as server-sent events, `gap` apart (`sleep:MS` is a silence, and
    /// a payload starting with `:` is sent as it is, a keep-alive comment); the stream ends
    /// after the last (a stream without `[DONE]` or a finish_reason is cut off), or when the
    /// client hangs up.
    pub fn events(events: Vec<String>, gap: Duration) -> Self {
        Self {
            events: Some((events, gap)),
            ..Self::raw(200, "")
        }
    }

    /// With a header.
    pub fn header(mut self, k: &str, v: &str) -> Self {
        self.headers.push((k.into(), v.into()));
        self
    }

    /// Answering after `d`.
    pub fn after(mut self, d: Duration) -> Self {
        self.delay = d;
        self
    }
}

/// A request as received.
#[derive(Clone, Debug)]
pub struct Recorded {
    pub method: String,
    pub path: String,
    pub headers: Vec<(String, String)>,
    pub body: String,
}

impl Recorded {
    pub fn header(&self, name: &str) -> Option<&str> {
        self.headers
            .iter()
            .find(|(k, _)| k.eq_ignore_ascii_case(name))
            .map(|(_, v)| v.as_str())
    }

    pub fn json(&self) -> serde_json::Value {
        serde_json::from_str(&self.body).expect("request bodies are JSON")
    }
}

/// The running server.
pub struct Server {
    /// Base URL, `http://127.0.0.1:PORT/v1`.
    pub url: String,
    pub requests: Arc<Mutex<Vec<Recorded>>>,
}

impl Server {
    /// Starts serving `replies` in order (a request beyond them gets a 500 saying so).
    pub fn start(replies: Vec<Canned>) -> Self {
        let listener = TcpListener::bind("127.0.0.1:0").expect("loopback bind");
        let port = listener.local_addr().unwrap().port();
        let requests = Arc::new(Mutex::new(Vec::new()));
        let rec = requests.clone();
        let replies = Arc::new(Mutex::new(
            replies
                .into_iter()
                .collect::<std::collections::VecDeque<_>>(),
        ));
        std::thread::spawn(move || {
            for stream in listener.incoming() {
                let Ok(mut stream) = stream else { continue };
                let mut reader = BufReader::new(stream.try_clone().unwrap());
                let mut line = String::new();
                if reader.read_line(&mut line).unwrap_or(0) == 0 {
                    continue;
                }
                let mut parts = line.split_whitespace();
                let method = parts.next().unwrap_or("").to_string();
                let path = parts.next().unwrap_or("").to_string();
                let mut headers = Vec::new();
                let mut len = 0usize;
                loop {
                    let mut h = String::new();
                    if reader.read_line(&mut h).unwrap_or(0) == 0 {
                        break;
                    }
                    let h = h.trim_end();
                    if h.is_empty() {
                        break;
                    }
                    if let Some((k, v)) = h.split_once(':') {
                        if k.eq_ignore_ascii_case("content-length") {
                            len = v.trim().parse().unwrap_or(0);
                        }
                        headers.push((k.trim().to_string(), v.trim().to_string()));
                    }
                }
                let mut body = vec![0u8; len];
                let _ = reader.read_exact(&mut body);
                let count = prompt_tokens(&String::from_utf8_lossy(&body));
                rec.lock().unwrap().push(Recorded {
                    method,
                    path,
                    headers,
                    body: String::from_utf8_lossy(&body).into_owned(),
                });
                let reply = replies.lock().unwrap().pop_front().unwrap_or_else(|| {
                    Canned::raw(
                        500,
                        r#"{"error": {"message": "the test server has no more replies"}}"#,
                    )
                });
                std::thread::sleep(reply.delay);
                let mut reply = reply;
                let placeholder = format!("\"{PROMPT_TOKENS}\"");
                reply.body = reply.body.replace(&placeholder, &count.to_string());
                if let Some((events, gap)) = &reply.events {
                    let _ = stream.write_all(
                        b"HTTP/1.1 200 OK\r\nContent-Type: text/event-stream\r\nCache-Control: no-cache\r\nConnection: close\r\n\r\n",
                    );
                    for e in events {
                        let e = e.replace(&placeholder, &count.to_string());
                        // `sleep:MS` holds the connection open, silent (a stalled stream).
                        if let Some(ms) = e.strip_prefix("sleep:") {
                            std::thread::sleep(Duration::from_millis(ms.parse().unwrap()));
                            continue;
                        }
                        let line = if e.starts_with(':') {
                            format!("{e}\n\n")
                        } else {
                            format!("data: {e}\n\n")
                        };
                        if stream
                            .write_all(line.as_bytes())
                            .and_then(|_| stream.flush())
                            .is_err()
                        {
                            break;
                        }
                        std::thread::sleep(*gap);
                    }
                    continue;
                }
                let mut head = format!(
                    "HTTP/1.1 {} X\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n",
                    reply.status,
                    reply.body.len()
                );
                for (k, v) in &reply.headers {
                    head.push_str(&format!("{k}: {v}\r\n"));
                }
                head.push_str("\r\n");
                let _ = stream.write_all(head.as_bytes());
                let _ = stream.write_all(reply.body.as_bytes());
                let _ = stream.flush();
            }
        });
        Server {
            url: format!("http://127.0.0.1:{port}/v1"),
            requests,
        }
    }

    /// The requests received so far.
    pub fn received(&self) -> Vec<Recorded> {
        self.requests.lock().unwrap().clone()
    }
}

/// A server for one request that reads it, answers with `head` (a status line and headers)
/// and leaves the rest of the answer to `then`: bodies no well-behaved server sends. Returns
/// the base URL.
pub fn one_shot(
    head: &'static [u8],
    then: impl FnOnce(&mut std::net::TcpStream) + Send + 'static,
) -> String {
    let listener = TcpListener::bind("127.0.0.1:0").unwrap();
    let url = format!(
        "http://127.0.0.1:{}/v1",
        listener.local_addr().unwrap().port()
    );
    std::thread::spawn(move || {
        let Ok((mut stream, _)) = listener.accept() else {
            return;
        };
        let mut request = [0u8; 65536];
        let _ = stream.read(&mut request);
        let _ = stream.write_all(head);
        then(&mut stream);
        // Keeps the listener (and so the port) until the client is done.
        std::thread::sleep(Duration::from_secs(30));
    });
    url
}

/// A loopback URL where nothing listens.
pub fn refused_url() -> String {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let port = l.local_addr().unwrap().port();
    drop(l);
    format!("http://127.0.0.1:{port}/v1")
}
