//! An OpenAI-compatible chat-completions client (OpenAI, Ollama's `/v1`, vLLM, llama.cpp's
//! server, LM Studio): one blocking POST per completion, retried with backoff on 429 and 5xx.
//!
//! The key travels only in the `Authorization` header: [`Exchange`] records the request body,
//! the URL without credentials and what came back, never the key.

use std::time::{Duration, Instant};

use serde::{Deserialize, Serialize};
use serde_json::{json, Value};

use super::clock::{abandoned, Abandoned, ReplyClock};
use super::LlmError;

/// How to reach the server.
#[derive(Clone)]
pub struct HttpConfig {
    /// Base URL (`http://127.0.0.1:11434/v1`); `/chat/completions` is appended unless the URL
    /// already ends with it.
    pub url: String,
    /// Model name as the server knows it.
    pub model: String,
    /// Bearer key, where the server needs one.
    pub key: Option<String>,
    /// Sampling temperature, always sent (Ollama's default is 1.0).
    pub temperature: f64,
    /// Most tokens in a reply.
    pub max_tokens: u32,
    /// The JSON field that carries `max_tokens`: `max_tokens` for most servers,
    /// `max_completion_tokens` for OpenAI's newer models.
    pub max_tokens_field: String,
    /// Whether to ask for the reply as a stream of events (`"stream": true`): signs of life
    /// from a slow model, and a stalled stream told apart from a slow one. A server that
    /// answers with plain JSON anyway is read as such.
    pub stream: bool,
    /// Seed sent with the request (servers treat it as best effort).
    pub seed: Option<u64>,
    /// Time to establish the connection.
    pub connect_timeout: Duration,
    /// The longest silence: for the reply's head, and for each read of its body; and the
    /// longest a streamed reply may go without a token, whatever else it sends (it may take
    /// longer in all, as long as tokens keep coming).
    pub read_timeout: Duration,
    /// The longest a reply may take in all, from the first request: retries, the waits
    /// between them and a reply that keeps coming without finishing included.
    pub reply_deadline: Duration,
    /// Attempts in all for 429 and 5xx answers (at least 1).
    pub attempts: u32,
    /// First wait between attempts; it doubles each time unless the server says
    /// `Retry-After`.
    pub backoff: Duration,
    /// The longest wait between attempts: the doubling stops there, and a `Retry-After` asking
    /// for more is cut to it (with a message), so that a server's absurd value cannot hang
    /// the run.
    pub backoff_max: Duration,
}

impl std::fmt::Debug for HttpConfig {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        // Never the key.
        f.debug_struct("HttpConfig")
            .field("url", &redact_url(&self.url))
            .field("model", &self.model)
            .field("key", &self.key.as_ref().map(|_| "(set)"))
            .field("temperature", &self.temperature)
            .finish_non_exhaustive()
    }
}

impl HttpConfig {
    /// Defaults for a server at `url` serving `model`.
    pub fn new(url: impl Into<String>, model: impl Into<String>) -> Self {
        Self {
            url: url.into(),
            model: model.into(),
            key: None,
            temperature: 0.2,
            max_tokens: 4096,
            max_tokens_field: "max_tokens".into(),
            stream: true,
            seed: None,
            connect_timeout: Duration::from_secs(10),
            read_timeout: Duration::from_secs(300),
            reply_deadline: Duration::from_secs(1800),
            attempts: 3,
            backoff: Duration::from_secs(2),
            backoff_max: Duration::from_secs(600),
        }
    }

    /// The endpoint the requests go to: `/chat/completions` joined to the URL's path, its
    /// query (a gateway's `?api-version=`) kept after it rather than swallowing the path.
    pub fn endpoint(&self) -> String {
        let join = |path: &str| {
            let p = path.trim_end_matches('/');
            if p.ends_with("/chat/completions") {
                p.to_string()
            } else {
                format!("{p}/chat/completions")
            }
        };
        match reqwest::Url::parse(&self.url) {
            Ok(mut u) if !u.cannot_be_a_base() => {
                let path = join(u.path());
                u.set_path(&path);
                u.set_fragment(None);
                u.to_string()
            }
            // Refused by `check`, which says why.
            _ => join(&self.url),
        }
    }

    /// Why this configuration cannot be sent, if it cannot: a URL that is not http(s) with a
    /// host, or a key an HTTP header cannot carry. Said before anything is read, naming the
    /// setting, rather than as the HTTP library's "builder error" (whose text can quote the
    /// URL's credentials).
    pub fn check(&self) -> Result<(), LlmError> {
        let shown = crate::io::name::shown_counted(&redact_url(&self.url));
        let bad = |why: &str| {
            LlmError::Setup(format!(
                "the LLM server URL \"{shown}\" (--llm-url or DRIVESCRIPT_LLM_URL) {why}"
            ))
        };
        // Every progress line and error names the URL: one of thousands of characters would
        // fill the terminal with each.
        let chars = self.url.chars().count();
        if chars > MAX_URL_CHARS {
            return Err(bad(&format!(
                "is {chars} characters long: at most {MAX_URL_CHARS}"
            )));
        }
        check_model(&self.model)?;
        let u = reqwest::Url::parse(&self.url).map_err(|e| bad(&format!("is not a URL: {e}")))?;
        if !matches!(u.scheme(), "http" | "https") {
            return Err(bad("must start with http:// or https://"));
        }
        // The URL standard skips any number of slashes after `http:`, so `http:///v1` (the
        // host left out) named host "v1", and the error was a failed connection to http://v1.
        let after_scheme = self.url.trim().split_once(':').map_or("", |(_, rest)| rest);
        let host_written = after_scheme
            .strip_prefix("//")
            .is_some_and(|rest| !rest.starts_with(['/', '\\']));
        if u.host_str().is_none_or(str::is_empty) || !host_written {
            return Err(bad(
                "names no host (write it right after `//`, as http://localhost:8080/v1)",
            ));
        }
        check_max_tokens_field(&self.max_tokens_field)?;
        if self
            .key
            .as_deref()
            .is_some_and(|k| k.chars().any(char::is_control))
        {
            return Err(LlmError::Setup(
                "DRIVESCRIPT_LLM_KEY holds a control character (a line break or tab pasted with \
                 the key?): an HTTP header cannot carry it"
                    .into(),
            ));
        }
        // Sent as raw UTF-8 bytes, such a key came back from a server that read the header as
        // Latin-1 (as HTTP's old rule has it) spelled otherwise (`sk-Ã¼…` for `sk-ü…`), which
        // no redaction of the key as written can find. Keys are ASCII.
        if self.key.as_deref().is_some_and(|k| !k.is_ascii()) {
            return Err(LlmError::Setup(
                "DRIVESCRIPT_LLM_KEY holds a character outside ASCII (a quote or dash an editor \
                 made typographic?): API keys are ASCII, and an HTTP header carries anything else \
                 as bytes a server may read differently"
                    .into(),
            ));
        }
        Ok(())
    }

    /// What this configuration sends that is secret, for redaction: the key, and the URL's
    /// password and query values (some gateways take the key there), as written and
    /// percent-decoded.
    fn secrets(&self) -> Vec<String> {
        let mut out: Vec<String> = self.key.iter().map(|k| k.trim().to_string()).collect();
        // The key percent-encoded too, as a proxy or server that echoes the request URL-encoded
        // writes it: a key holding `+`, `/` or `=` (`openssl rand -base64 32`, which vLLM's
        // --api-key takes) was shown whole in that form ("Bearer%20abc%2Bdef%2F...").
        for k in self.key.iter().map(|k| k.trim()) {
            for upper in [true, false] {
                let encoded = percent_encode(k, upper);
                if encoded != k {
                    out.push(encoded);
                }
            }
        }
        // And base64-encoded, as a server that echoes the raw header block or a `Basic`-style
        // blob writes it: within any base64 text the key lands at one of three alignments,
        // and each has a run of characters that only the key's bytes decide.
        for k in self.key.iter().map(|k| k.trim()) {
            out.extend(base64_cores(k.as_bytes()));
            // And the base64 of its percent-encoded form, as a server that base64-encodes the
            // request URL or a form body it echoes writes it (a key of unreserved characters
            // is the same encoded, and was covered above).
            for upper in [true, false] {
                let encoded = percent_encode(k, upper);
                if encoded != k {
                    out.extend(base64_cores(encoded.as_bytes()));
                }
            }
        }
        if let Ok(u) = reqwest::Url::parse(&self.url) {
            let password = u.password().map(str::to_string);
            let query = u.query().into_iter().flat_map(|q| {
                q.split('&')
                    .filter_map(|kv| kv.split_once('=').map(|(_, v)| v.to_string()))
                    .collect::<Vec<_>>()
            });
            if let Some(p) = &password {
                // As the HTTP library sends it, in an `Authorization: Basic` header.
                let pair = format!("{}:{}", percent_decode(u.username()), percent_decode(p));
                out.push(base64(pair.as_bytes()));
            } else if !u.username().is_empty() {
                // `http://KEY@host/v1`: with no password the user name is the credential, and
                // travels as the `Basic` token of "KEY:".
                let user = percent_decode(u.username());
                out.push(base64(format!("{user}:").as_bytes()));
                out.push(user);
                out.push(u.username().to_string());
            }
            for s in password.into_iter().chain(query) {
                out.push(percent_decode(&s));
                out.push(s);
            }
        }
        out
    }
}

/// The fields every request body sets itself ([`HttpClient::body`]): a token limit sent under
/// one of these names would replace it.
const BODY_FIELDS: [&str; 6] = [
    "model",
    "messages",
    "temperature",
    "stream",
    "stream_options",
    "seed",
];

/// The longest LLM server URL taken (`--llm-url`), characters.
pub const MAX_URL_CHARS: usize = 2048;

/// The longest model name taken (`--model`), characters: model ids with a repository and a
/// quantisation (`hf.co/org/Model-GGUF:Q4_K_M`) are under a hundred.
pub const MAX_MODEL_CHARS: usize = 256;

/// Whether `model` can be a model name (`--model`, `DRIVESCRIPT_LLM_MODEL`): 1 to
/// [`MAX_MODEL_CHARS`] characters, none a control or invisible one. It is printed with every
/// round and recorded in the run; a long one was echoed whole in each line.
pub fn check_model(model: &str) -> Result<(), LlmError> {
    let bad = |why: String| {
        Err(LlmError::Setup(format!(
            "the model name \"{}\" (--model or DRIVESCRIPT_LLM_MODEL) {why}",
            crate::io::name::shown_counted(model)
        )))
    };
    let chars = model.chars().count();
    if model.trim().is_empty() {
        return bad("is empty".into());
    }
    if chars > MAX_MODEL_CHARS {
        return bad(format!(
            "is {chars} characters long: at most {MAX_MODEL_CHARS}"
        ));
    }
    if let Err(c) = crate::io::name::check_name(model) {
        return bad(format!("holds {c}"));
    }
    Ok(())
}

/// Whether `field` can carry the token limit (`--max-tokens-field`): a JSON field name a
/// server reads, 1 to 64 ASCII letters, digits and `_` (`max_tokens`,
/// `max_completion_tokens`), and not a field the request already sends.
pub fn check_max_tokens_field(field: &str) -> Result<(), LlmError> {
    let bad = |why: &str| {
        Err(LlmError::Setup(format!(
            "--max-tokens-field \"{}\": {why} (max_tokens for most servers, \
             max_completion_tokens for OpenAI's newer models)",
            crate::io::name::shown_counted(field)
        )))
    };
    if field.is_empty() || field.len() > 64 {
        return bad("must be 1 to 64 characters");
    }
    if !field
        .bytes()
        .all(|b| b.is_ascii_alphanumeric() || b == b'_')
    {
        return bad("a request field name is ASCII letters, digits and `_` only");
    }
    if BODY_FIELDS.contains(&field) {
        return bad("the request already sends that field");
    }
    Ok(())
}

/// Standard base64 with padding, as an `Authorization: Basic` header carries `user:password`.
fn base64(bytes: &[u8]) -> String {
    const A: &[u8; 64] = b"ABCDEFGHIJKLMNOPQRSTUVWXYZabcdefghijklmnopqrstuvwxyz0123456789+/";
    let mut out = String::with_capacity(bytes.len().div_ceil(3) * 4);
    for chunk in bytes.chunks(3) {
        let n = chunk
            .iter()
            .enumerate()
            .fold(0u32, |n, (i, &b)| n | (b as u32) << (16 - 8 * i));
        for i in 0..4 {
            if i <= chunk.len() {
                out.push(A[(n >> (18 - 6 * i) & 63) as usize] as char);
            } else {
                out.push('=');
            }
        }
    }
    out
}

/// The parts of any base64 text holding `bytes` that `bytes` alone decide, one for each of the
/// three alignments the bytes can have there, in the standard and the URL-safe alphabet: the
/// characters that also encode a neighbouring byte are left off both ends.
fn base64_cores(bytes: &[u8]) -> Vec<String> {
    let mut out = Vec::new();
    for offset in 0..3 {
        let mut padded = vec![0u8; offset];
        padded.extend_from_slice(bytes);
        let encoded = base64(&padded);
        // Characters wholly inside the bytes: from the first 6-bit group that starts at or
        // after bit 8·offset to the last one that ends at or before the bytes' end.
        let from = (8 * offset).div_ceil(6);
        let to = (8 * padded.len()) / 6;
        if to <= from + 4 {
            continue;
        }
        let core = &encoded[from..to];
        out.push(core.to_string());
        let url_safe = core.replace('+', "-").replace('/', "_");
        if url_safe != core {
            out.push(url_safe);
        }
    }
    out
}

/// `s` with every byte but URL's unreserved ones (letters, digits, `-`, `.`, `_`, `~`) written
/// as `%XX`, in upper- or lower-case hex.
fn percent_encode(s: &str, upper: bool) -> String {
    let mut out = String::with_capacity(s.len());
    for &b in s.as_bytes() {
        if b.is_ascii_alphanumeric() || b"-._~".contains(&b) {
            out.push(b as char);
        } else if upper {
            out.push_str(&format!("%{b:02X}"));
        } else {
            out.push_str(&format!("%{b:02x}"));
        }
    }
    out
}

/// `s` with its `%XX` escapes decoded (bytes that do not make UTF-8 replaced).
fn percent_decode(s: &str) -> String {
    let b = s.as_bytes();
    let hex = |i: usize| b.get(i).and_then(|&c| (c as char).to_digit(16));
    let mut out = Vec::with_capacity(b.len());
    let mut i = 0;
    while i < b.len() {
        match (b[i], hex(i + 1), hex(i + 2)) {
            (b'%', Some(h), Some(l)) => {
                out.push((h * 16 + l) as u8);
                i += 3;
            }
            (c, _, _) => {
                out.push(c);
                i += 1;
            }
        }
    }
    String::from_utf8_lossy(&out).into_owned()
}

/// The URL with any `user:password@` removed and its query and fragment dropped (some
/// gateways take the key there), for transcripts and messages. Whatever precedes the URL's
/// last `@` goes, not only what precedes the first `/`: a password typed with a `/` in it
/// (`http://u:p/ss@host`) makes no URL userinfo, but it is still a secret.
pub fn redact_url(url: &str) -> String {
    let (scheme, rest) = match url.split_once("://") {
        Some((s, r)) => (Some(s), r),
        None => (None, url),
    };
    let rest = rest.split(['?', '#']).next().unwrap_or("");
    let rest = rest.rsplit_once('@').map_or(rest, |(_, r)| r);
    match scheme {
        Some(s) => format!("{s}://{rest}"),
        None => rest.to_string(),
    }
}

/// One chat message.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Message {
    /// `system`, `user` or `assistant`.
    pub role: String,
    /// Its text.
    pub content: String,
}

impl Message {
    /// A message with this role.
    pub fn new(role: &str, content: impl Into<String>) -> Self {
        Self {
            role: role.into(),
            content: content.into(),
        }
    }
}

/// Token counts the server reported.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
pub struct Usage {
    /// Prompt tokens.
    pub prompt_tokens: u64,
    /// Completion tokens.
    pub completion_tokens: u64,
}

/// One completion with what it took: what a transcript records.
#[derive(Debug, Clone, Serialize)]
pub struct Exchange {
    /// Endpoint, without credentials.
    pub url: String,
    /// The request body as sent (model, messages, temperature, ...).
    pub request: Value,
    /// The reply's text.
    pub reply: String,
    /// Token usage, when the server reported it.
    pub usage: Option<Usage>,
    /// The prompt's tokens as estimated before sending ([`super::budget::estimate_tokens`]).
    pub estimated_prompt_tokens: u64,
    /// Seconds from the first attempt to the reply.
    pub latency: f64,
    /// Attempts that failed and were retried, each as `status: message (waited N s)`.
    pub retries: Vec<String>,
    /// The reply came as a stream of events.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub streamed: bool,
    /// The server stopped the reply at the token limit (`finish_reason: "length"`): a script
    /// in it may be cut off.
    #[serde(skip_serializing_if = "std::ops::Not::not")]
    pub truncated: bool,
}

/// What the client tells its observer while a completion is under way.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum ClientEvent<'a> {
    /// A line to show now, whatever the terminal (a `Retry-After` cut to the backoff ceiling).
    Notice(&'a str),
    /// A streamed reply is coming: `tokens` so far, the time since the first of them and the
    /// time since the request was sent (a terminal shows [`super::stream::progress_line`]).
    Streaming {
        /// Chunks with content so far.
        tokens: usize,
        /// Since the first token.
        since_first: Option<Duration>,
        /// Since the request was sent.
        elapsed: Duration,
    },
    /// The streamed reply is complete (or failed): a progress line can go.
    StreamEnd,
}

/// Receives [`ClientEvent`]s (the CLI prints them).
pub type Observer = std::sync::Arc<dyn Fn(ClientEvent<'_>) + Send + Sync>;

/// A blocking chat-completions client.
#[derive(Clone)]
pub struct HttpClient {
    cfg: HttpConfig,
    http: reqwest::blocking::Client,
    observer: Option<Observer>,
    /// [`HttpConfig::secrets`], kept out of everything the server sends back.
    secrets: Vec<String>,
}

/// How long to wait before the next attempt, and the note that says why: the server's
/// `Retry-After` when it gave one, cut to `ceiling`, else the backoff.
fn retry_pause(
    retry_after: Option<f64>,
    backoff: Duration,
    ceiling: Duration,
) -> (Duration, String) {
    match retry_after {
        Some(s) if s > ceiling.as_secs_f64() => (
            ceiling,
            format!(
                ", not the {} s Retry-After asked: capped at the backoff ceiling, --backoff-max {} s",
                crate::geom::num(s),
                crate::geom::num(ceiling.as_secs_f64())
            ),
        ),
        Some(s) => (Duration::from_secs_f64(s), ", as Retry-After asked".into()),
        None => (backoff.min(ceiling), String::new()),
    }
}

impl HttpClient {
    /// A client for `cfg`.
    pub fn new(cfg: HttpConfig) -> Result<Self, LlmError> {
        cfg.check()?;
        let http = reqwest::blocking::Client::builder()
            .connect_timeout(cfg.connect_timeout)
            .timeout(cfg.read_timeout)
            .redirect(reqwest::redirect::Policy::custom(follow_redirect))
            .build()
            .map_err(|e| LlmError::Setup(format!("HTTP client: {e}")))?;
        Ok(Self {
            secrets: cfg.secrets(),
            cfg,
            http,
            observer: None,
        })
    }

    /// The client telling `observer` what happens while a completion is under way.
    pub fn with_observer(mut self, observer: Observer) -> Self {
        self.observer = Some(observer);
        self
    }

    /// A prompt the server reports much shorter than the one sent was cut to its context
    /// window: an error naming the fix for the server, not a reply to a prompt the model
    /// never saw whole.
    fn check_context(
        &self,
        url: &str,
        estimate: u64,
        usage: Option<Usage>,
        fingerprint: Option<&str>,
    ) -> Result<(), LlmError> {
        let Some(u) = usage else { return Ok(()) };
        let kind = super::budget::ServerKind::detect(&self.cfg.url, fingerprint);
        match super::budget::check_prompt_tokens(
            estimate,
            u.prompt_tokens,
            u64::from(self.cfg.max_tokens),
            kind,
        ) {
            None => Ok(()),
            Some(message) => Err(LlmError::ContextCut {
                url: url.into(),
                message,
            }),
        }
    }

    /// The completion in a successful reply: a stream of events, or (from a server that does
    /// not stream, or was not asked to) one JSON body.
    fn read_completion(
        &self,
        resp: reqwest::blocking::Response,
        url: &str,
        clock: &ReplyClock,
    ) -> Result<Completion, LlmError> {
        use std::io::BufRead;
        if let Some(encoding) = self.compressed(&resp) {
            return Err(LlmError::BadReply {
                url: url.into(),
                message: format!(
                    "the server sent the reply compressed (Content-Encoding: {encoding}), though \
                     the request asks for no compression (it sends no Accept-Encoding): a proxy \
                     between may be compressing it; turn that off, or point --llm-url past it"
                ),
            });
        }
        let status = resp.status().as_u16();
        let content_type = resp
            .headers()
            .get(reqwest::header::CONTENT_TYPE)
            .and_then(|v| v.to_str().ok())
            .map(str::to_string);
        let mut body = std::io::BufReader::new(clock.reader(resp, false));
        let head = body
            .fill_buf()
            .map_err(|e| read_error(&e, url, &self.cfg, clock, 0))?;
        if !(self.cfg.stream && super::stream::is_event_stream(content_type.as_deref(), head)) {
            // A completion is JSON, which is UTF-8: lossy decoding stored U+FFFD in the reply
            // without a word.
            let raw = String::from_utf8(read_body(body, url, &self.cfg, clock)?).map_err(|e| {
                LlmError::BadReply {
                    url: url.into(),
                    message: format!(
                        "the reply body (HTTP {status}) is not UTF-8 (byte {}), as JSON must be: \
                         the server is broken or sends another encoding",
                        e.utf8_error().valid_up_to() + 1
                    ),
                }
            })?;
            let text = self.redact(&raw);
            if text.trim().is_empty() {
                return Err(LlmError::BadReply {
                    url: url.into(),
                    message: format!(
                        "the server answered HTTP {status} with an empty body, no completion: is \
                         the URL an OpenAI-compatible chat-completions API (it usually ends in /v1)?"
                    ),
                });
            }
            return parse_completion_redacted(&text, url, &|s| self.redact(s))
                .map_err(|e| self.redact_error(e));
        }
        let observe = |e: ClientEvent<'_>| {
            if let Some(o) = &self.observer {
                o(e)
            }
        };
        let got = super::stream::read_stream(
            body,
            url,
            clock,
            &|e, n| read_error(e, url, &self.cfg, clock, n),
            &|s| self.redact(s),
            &mut |tokens, since_first| {
                observe(ClientEvent::Streaming {
                    tokens,
                    since_first,
                    elapsed: clock.elapsed(),
                })
            },
        );
        observe(ClientEvent::StreamEnd);
        let got = got.map_err(|e| self.redact_error(e))?;
        Ok(Completion {
            content: got.content,
            usage: got.usage,
            truncated: got.truncated,
            fingerprint: got.fingerprint,
            streamed: true,
        })
    }

    fn notice(&self, line: &str) {
        if let Some(o) = &self.observer {
            o(ClientEvent::Notice(line));
        }
    }

    /// The client sending `seed` with every request ([`HttpConfig::seed`]).
    pub fn with_seed(mut self, seed: Option<u64>) -> Self {
        self.cfg.seed = seed;
        self
    }

    /// The client asking for replies of at most `max_tokens` ([`HttpConfig::max_tokens`]).
    pub fn with_max_tokens(mut self, max_tokens: u32) -> Self {
        self.cfg.max_tokens = max_tokens;
        self
    }

    /// The settings.
    pub fn config(&self) -> &HttpConfig {
        &self.cfg
    }

    /// The request body for `messages`.
    pub fn body(&self, messages: &[Message]) -> Value {
        let mut body = json!({
            "model": self.cfg.model,
            "messages": messages,
            "temperature": self.cfg.temperature,
            "stream": self.cfg.stream,
        });
        if self.cfg.stream {
            // The usage comes in a last chunk only when asked for (OpenAI, vLLM, Ollama).
            body["stream_options"] = json!({"include_usage": true});
        }
        body[self.cfg.max_tokens_field.as_str()] = json!(self.cfg.max_tokens);
        if let Some(s) = self.cfg.seed {
            body["seed"] = json!(s);
        }
        body
    }

    /// Sends `messages` and returns the first choice's text.
    pub fn complete(&self, messages: &[Message]) -> Result<Exchange, LlmError> {
        let url = self.cfg.endpoint();
        let shown = redact_url(&url);
        let body = self.body(messages);
        let estimate = super::budget::estimate_tokens(messages);
        let t0 = Instant::now();
        let clock = ReplyClock::new(t0, self.cfg.reply_deadline, self.cfg.read_timeout);
        let mut retries = Vec::new();
        let attempts = self.cfg.attempts.max(1);
        let mut wait = self.cfg.backoff;
        for attempt in 1..=attempts {
            let mut req = self.http.post(&url).json(&body);
            if let Some(k) = &self.cfg.key {
                req = req.bearer_auth(k);
            }
            // The silence limit, cut to the time left: a server silent at the deadline is
            // given up on at it. (A request's own timeout also bounds its whole body, so it
            // can only be set where it is shorter than the silence limit.)
            let left = clock.remaining();
            if left < self.cfg.read_timeout {
                req = req.timeout(left.max(Duration::from_millis(1)));
            }
            let resp = match req.send() {
                Ok(r) => r,
                Err(e) => {
                    return Err(match transport_error(&e, &shown, &self.cfg) {
                        LlmError::Timeout { .. } if clock.expired() => {
                            clock.past_deadline(&shown, "no reply head")
                        }
                        other => self.redact_error(other),
                    })
                }
            };
            let status = resp.status().as_u16();
            let retry_after = resp
                .headers()
                .get(reqwest::header::RETRY_AFTER)
                .and_then(|v| v.to_str().ok())
                .and_then(|v| {
                    v.trim()
                        .parse::<f64>()
                        .ok()
                        .or_else(|| seconds_until_http_date(v, std::time::SystemTime::now()))
                })
                .filter(|s| s.is_finite() && *s >= 0.0);
            if let Some(location) = resp
                .headers()
                .get(reqwest::header::LOCATION)
                .filter(|_| (300..400).contains(&status))
            {
                return Err(self.redirect_error(&shown, status, resp.url(), location));
            }
            if (200..300).contains(&status) {
                let got = self.read_completion(resp, &shown, &clock)?;
                if got.content.len() > MAX_COMPLETION_BYTES {
                    return Err(LlmError::BadReply {
                        url: shown,
                        message: format!(
                            "the completion's text is {:.1} MB, over the {} MB drivescript \
                             keeps (a cost script is a few KB): the server ignored the token \
                             limit ({} tokens, --max-tokens) or is broken",
                            got.content.len() as f64 / (1 << 20) as f64,
                            MAX_COMPLETION_BYTES >> 20,
                            self.cfg.max_tokens
                        ),
                    });
                }
                self.check_context(&shown, estimate, got.usage, got.fingerprint.as_deref())?;
                return Ok(Exchange {
                    url: shown,
                    request: body,
                    // Again after decoding: JSON escapes (`\u0073k-...`) hide it from the first.
                    reply: self.redact(&got.content),
                    usage: got.usage,
                    estimated_prompt_tokens: estimate,
                    latency: t0.elapsed().as_secs_f64(),
                    retries,
                    streamed: got.streamed,
                    truncated: got.truncated,
                });
            }
            let message = match self.compressed(&resp) {
                // Its bytes quoted as text say nothing.
                Some(encoding) => format!("(a body compressed as {encoding}, not read)"),
                None => {
                    let text = self.redact(&String::from_utf8_lossy(&read_body(
                        clock.reader(resp, false),
                        &shown,
                        &self.cfg,
                        &clock,
                    )?));
                    error_message_redacted(&text, &|s| self.redact(s))
                }
            };
            let retryable = status == 429 || (500..600).contains(&status);
            if !retryable {
                return Err(match status {
                    401 | 403 => LlmError::Auth {
                        url: shown,
                        status,
                        message,
                    },
                    404 => LlmError::NotFound {
                        url: shown,
                        model: self.cfg.model.clone(),
                        message,
                    },
                    _ => LlmError::Status {
                        url: shown,
                        status,
                        attempts: attempt,
                        message,
                    },
                });
            }
            if attempt == attempts {
                return Err(LlmError::Status {
                    url: shown,
                    status,
                    attempts,
                    message,
                });
            }
            let (pause, note) = retry_pause(retry_after, wait, self.cfg.backoff_max);
            if pause >= clock.remaining() {
                return Err(LlmError::Status {
                    url: shown,
                    status,
                    attempts: attempt,
                    message: format!(
                        "{message}; no further attempt: the wait of {:.1} s{note} would pass the \
                         reply deadline of {} s (--reply-deadline)",
                        pause.as_secs_f64(),
                        crate::geom::num(clock.deadline().as_secs_f64())
                    ),
                });
            }
            let line = format!(
                "{status}: {message} (waited {:.1} s{note})",
                pause.as_secs_f64()
            );
            if retry_after.is_some_and(|s| s > self.cfg.backoff_max.as_secs_f64()) {
                self.notice(&format!("{shown}: {line}"));
            }
            retries.push(line);
            std::thread::sleep(pause);
            wait = (wait * 2).min(self.cfg.backoff_max);
        }
        unreachable!("the last attempt returns")
    }
}

/// Seconds from `now` until the HTTP date `v` (`Wed, 21 Oct 2099 07:28:00 GMT`, the form HTTP
/// requires a sender to use), which `Retry-After` may carry instead of a number of seconds: it
/// was ignored, and the request retried after the plain backoff without a word. 0 for a date
/// already past; `None` for anything else.
fn seconds_until_http_date(v: &str, now: std::time::SystemTime) -> Option<f64> {
    const MONTHS: [&str; 12] = [
        "Jan", "Feb", "Mar", "Apr", "May", "Jun", "Jul", "Aug", "Sep", "Oct", "Nov", "Dec",
    ];
    let parts: Vec<&str> = v.split_ascii_whitespace().collect();
    let [weekday, day, month, year, time, "GMT"] = parts[..] else {
        return None;
    };
    if !weekday.ends_with(',') {
        return None;
    }
    let day: i64 = day.parse().ok().filter(|d| (1..=31).contains(d))?;
    let month = MONTHS.iter().position(|m| *m == month)? as i64 + 1;
    let year: i64 = year.parse().ok().filter(|y| (1970..=9999).contains(y))?;
    let hms: Vec<i64> = time
        .split(':')
        .map(|x| x.parse().ok())
        .collect::<Option<Vec<i64>>>()?;
    let [h, m, sec] = hms[..] else { return None };
    if !((0..24).contains(&h) && (0..60).contains(&m) && (0..=60).contains(&sec)) {
        return None;
    }
    // Days since 1970-01-01 of a proleptic Gregorian date (H. Hinnant's days_from_civil).
    let y = if month <= 2 { year - 1 } else { year };
    let era = y.div_euclid(400);
    let yoe = y - era * 400;
    let doy = (153 * ((month + 9) % 12) + 2) / 5 + day - 1;
    let doe = yoe * 365 + yoe / 4 - yoe / 100 + doy;
    let at = (era * 146_097 + doe - 719_468) * 86_400 + h * 3600 + m * 60 + sec;
    let now = now
        .duration_since(std::time::UNIX_EPOCH)
        .ok()?
        .as_secs_f64();
    Some((at as f64 - now).max(0.0))
}

/// Which redirects the client follows: a 307 or 308 (which keep the method and the body) to
/// the same scheme, host and port, at most 4 in a row. Any other answers as it is, and
/// [`HttpClient::complete`] says where it points: followed, a redirect sent the prompt (and,
/// to the same host, the key) wherever a server named, off the loopback interface too, and a
/// 301, 302 or 303 turned the request into a GET without its body, answered by an error that
/// named only the URL the user gave.
fn follow_redirect(attempt: reqwest::redirect::Attempt<'_>) -> reqwest::redirect::Action {
    let origin = |u: &reqwest::Url| {
        (
            u.scheme().to_string(),
            u.host_str().map(str::to_string),
            u.port_or_known_default(),
        )
    };
    let same = attempt
        .previous()
        .last()
        .is_some_and(|p| origin(p) == origin(attempt.url()));
    if same && matches!(attempt.status().as_u16(), 307 | 308) && attempt.previous().len() <= 4 {
        attempt.follow()
    } else {
        attempt.stop()
    }
}

/// The most a reply body may hold: a completion is a few KB; an endless body (a broken or
/// hostile server) must end in an error, not fill memory until the process aborts.
pub const MAX_REPLY_BYTES: u64 = 16 << 20;

/// The most a completion's text may hold: 1 MB, about 250,000 tokens, sixty times the default
/// `--max-tokens`. A cost script's reply is a few KB, yet every reply is kept in the run
/// directory (`messages.json`, `state.json`, `transcript.json`, rewritten each round) and sent
/// back with every later round: a server that ignored the token limit and answered 10 MB twice
/// made a 96 MB run directory, and twenty such rounds would have written gigabytes.
pub const MAX_COMPLETION_BYTES: usize = 1 << 20;

/// Reads a reply body's bytes within [`MAX_REPLY_BYTES`]; `resp` is read under `clock`
/// ([`ReplyClock::reader`]).
fn read_body(
    resp: impl std::io::Read,
    url: &str,
    cfg: &HttpConfig,
    clock: &ReplyClock,
) -> Result<Vec<u8>, LlmError> {
    use std::io::Read;
    let mut buf = Vec::new();
    if let Err(e) = resp.take(MAX_REPLY_BYTES + 1).read_to_end(&mut buf) {
        return Err(read_error(&e, url, cfg, clock, buf.len()));
    }
    if buf.len() as u64 > MAX_REPLY_BYTES {
        return Err(LlmError::BadReply {
            url: url.into(),
            message: format!(
                "the reply is larger than {} MB: no completion is; the server is broken or \
                 not an LLM server",
                MAX_REPLY_BYTES >> 20
            ),
        });
    }
    Ok(buf)
}

/// What a failed read of a reply body means: the reply's deadline passed ([`ReplyClock`]),
/// the silence limit passed (a timeout), the server reset or closed the connection in the
/// middle (a reset: the server died, or a proxy cut it; not worth waiting out the timeout
/// for), or something else. `got` bytes had arrived.
fn read_error(
    e: &std::io::Error,
    url: &str,
    cfg: &HttpConfig,
    clock: &ReplyClock,
    got: usize,
) -> LlmError {
    use std::io::ErrorKind as K;
    let past_deadline = || clock.past_deadline(url, &format!("{got} bytes of the body"));
    match abandoned(e) {
        Some(Abandoned::Deadline) => return past_deadline(),
        // Only a stream watches for tokens, and it says so itself.
        Some(Abandoned::NoProgress) | None => {}
    }
    // The cause is several layers down (io, reqwest, hyper, io): every layer is looked at.
    let mut chain = vec![e.to_string()];
    let mut kinds = vec![e.kind()];
    let mut src: Option<&(dyn std::error::Error + 'static)> = e.get_ref().map(|r| r as _);
    while let Some(s) = src {
        // An io::Error shows its inner error's text, so that layer would be said twice.
        let text = s.to_string();
        if chain.last() != Some(&text) {
            chain.push(text);
        }
        if let Some(io) = s.downcast_ref::<std::io::Error>() {
            kinds.push(io.kind());
        }
        src = s.source();
    }
    let text = chain.join(": ").to_lowercase();
    if kinds.contains(&K::TimedOut) || text.contains("timed out") {
        if clock.expired() {
            return past_deadline();
        }
        return LlmError::Timeout {
            url: url.into(),
            seconds: cfg.read_timeout.as_secs_f64(),
            connecting: false,
        };
    }
    let reset = kinds
        .iter()
        .any(|k| matches!(k, K::ConnectionReset | K::ConnectionAborted | K::BrokenPipe))
        || text.contains("reset")
        || text.contains("closed before message completed")
        || text.contains("unexpected eof")
        || kinds.contains(&K::UnexpectedEof);
    if reset {
        return LlmError::Reset {
            url: url.into(),
            bytes: got,
            message: chain.last().cloned().unwrap_or_default(),
        };
    }
    LlmError::Transport {
        url: url.into(),
        message: format!("reading the reply: {}", chain.join(": ")),
    }
}

/// `text` with every occurrence of `key` replaced by `[redacted]`, in any letter case, also
/// where whitespace or invisible characters were put inside it, and where any of its characters
/// are written as escapes (`%73`, `&#115;`, `&#x73;`, `\u0073`, `\x73`): a server that wrapped
/// the echoed key across lines (`sk-TES\nT123xyz`), wrote it in capitals, spaced it with zero-width
/// characters or echoed it as HTML entities showed it to anyone who read the text as it is
/// meant to be read. Keys shorter than 8 bytes are left alone: no real key is that short, and
/// replacing a common word everywhere would garble replies.
pub fn redact_key(text: &str, key: Option<&str>) -> String {
    let Some(k) = key.map(str::trim).filter(|k| k.len() >= 8) else {
        return text.to_string();
    };
    let text = if text.contains(k) {
        text.replace(k, "[redacted]")
    } else {
        text.to_string()
    };
    let want: Vec<char> = k.chars().filter(|c| !c.is_whitespace()).collect();
    let chars: Vec<(usize, char)> = text.char_indices().collect();
    let mut out = String::with_capacity(text.len());
    let (mut i, mut copied) = (0, 0);
    while i < chars.len() {
        let Some((first, len)) = escaped_unit(&chars, i) else {
            break;
        };
        if !first.eq_ignore_ascii_case(&want[0]) {
            i += 1;
            continue;
        }
        // Match the key's characters in order, skipping what cannot be seen between them.
        let (mut j, mut m) = (i + len, 1);
        while m < want.len() {
            let Some((c, len)) = escaped_unit(&chars, j) else {
                break;
            };
            if c.eq_ignore_ascii_case(&want[m]) {
                m += 1;
            } else if !(c.is_whitespace() || invisible(c)) {
                break;
            }
            j += len;
        }
        if m == want.len() {
            out.push_str(&text[copied..chars[i].0]);
            out.push_str("[redacted]");
            copied = chars.get(j).map_or(text.len(), |c| c.0);
            i = j;
        } else {
            i += 1;
        }
    }
    out.push_str(&text[copied..]);
    out
}

/// The character at `chars[i]` as a reader of the text would see it, and how many characters
/// it takes: itself, or the character a percent, HTML or backslash escape starting there
/// stands for. `None` past the end.
fn escaped_unit(chars: &[(usize, char)], i: usize) -> Option<(char, usize)> {
    let c = chars.get(i)?.1;
    let at = |k: usize| chars.get(i + k).map(|c| c.1);
    // Up to `max` digits of `radix` from offset `from`: the value and how many were read.
    let digits = |from: usize, radix: u32, max: usize| {
        let mut v: u32 = 0;
        let mut n = 0;
        while n < max {
            match at(from + n).and_then(|c| c.to_digit(radix)) {
                Some(d) => v = v.saturating_mul(radix).saturating_add(d),
                None => break,
            }
            n += 1;
        }
        (v, n)
    };
    // Whether the characters from offset `from` spell `word`, in any letter case.
    let spells = |from: usize, word: &str| {
        word.chars()
            .enumerate()
            .all(|(k, w)| at(from + k).is_some_and(|c| c.eq_ignore_ascii_case(&w)))
    };
    let decoded = match c {
        '%' => {
            // Encoded twice or more (`%2573`, the `%` of `%73` itself encoded as `%25`), as a
            // proxy that encodes what a server already encoded writes it: a `25` is skipped
            // while another hex pair follows it.
            let mut p = 1;
            while spells(p, "25") && digits(p + 2, 16, 2).1 == 2 {
                p += 2;
            }
            match digits(p, 16, 2) {
                (v, 2) if v < 0x80 => Some((v, p + 2)),
                _ => None,
            }
        }
        '&' => {
            // `&amp;#115;`: an entity whose `&` was itself escaped, as text HTML-escaped twice
            // shows it (the key was shown whole in that form); any number of `amp;`.
            let mut p = 1;
            while spells(p, "amp;") {
                p += 4;
            }
            // The named entities of the characters a key holds besides letters and digits
            // (`openssl rand -base64` keys hold `+`, `/` and `=`).
            let named = [
                ("plus;", '+'),
                ("sol;", '/'),
                ("equals;", '='),
                ("lowbar;", '_'),
                ("period;", '.'),
                ("colon;", ':'),
                ("percnt;", '%'),
                ("num;", '#'),
            ]
            .into_iter()
            .find(|(w, _)| spells(p, w))
            .map(|(w, ch)| (ch as u32, p + w.len()));
            if at(p) == Some('#') {
                let hex = matches!(at(p + 1), Some('x' | 'X'));
                let from = if hex { p + 2 } else { p + 1 };
                let (v, n) = digits(from, if hex { 16 } else { 10 }, 8);
                (n > 0 && at(from + n) == Some(';')).then_some((v, from + n + 1))
            } else if named.is_some() {
                named
            } else {
                (p > 1).then_some(('&' as u32, p))
            }
        }
        '\\' if at(1) == Some('u') => match digits(2, 16, 4) {
            (v, 4) => Some((v, 6)),
            _ => None,
        },
        '\\' if at(1) == Some('x') => match digits(2, 16, 2) {
            (v, 2) => Some((v, 4)),
            _ => None,
        },
        _ => None,
    };
    Some(
        decoded
            .and_then(|(v, n)| char::from_u32(v).map(|c| (c, n)))
            .unwrap_or((c, 1)),
    )
}

/// Characters that print as nothing: zero-width spaces and joiners, the soft hyphen, bidi
/// marks and controls, variation selectors and the byte-order mark.
fn invisible(c: char) -> bool {
    matches!(c,
        '\u{ad}' | '\u{34f}' | '\u{61c}' | '\u{180e}' | '\u{200b}'..='\u{200f}'
        | '\u{202a}'..='\u{202e}' | '\u{2060}'..='\u{206f}' | '\u{fe00}'..='\u{fe0f}'
        | '\u{feff}')
}

impl HttpClient {
    /// Everything the server sends passes here before anyone else sees it: a server that
    /// echoes the `Authorization` header (in an error body, or quoted in a completion) must not
    /// get the key onto the terminal or into the run directory's files, nor the password or
    /// query values of the URL (nor the `Basic` token the password travels as).
    fn redact(&self, text: &str) -> String {
        self.secrets
            .iter()
            .fold(text.to_string(), |t, s| redact_key(&t, Some(s)))
    }

    /// A redirect the client did not follow ([`follow_redirect`]), with where it points
    /// (resolved against the URL that answered, its credentials and query left out).
    fn redirect_error(
        &self,
        url: &str,
        status: u16,
        answered: &reqwest::Url,
        location: &reqwest::header::HeaderValue,
    ) -> LlmError {
        let raw = String::from_utf8_lossy(location.as_bytes()).into_owned();
        let target = match answered.join(raw.trim()) {
            Ok(t) => {
                let loop_note = if t == *answered {
                    " (itself: a redirect loop)"
                } else {
                    ""
                };
                format!("{}{loop_note}", redact_url(t.as_str()))
            }
            Err(_) => format!("{:?}, not a URL", redact_url(&raw)),
        };
        // A URL holds no control character (the parser escapes them); a huge header is cut.
        let whole = self.redact(&target);
        let mut location: String = whole.chars().take(300).collect();
        if location.len() < whole.len() {
            location.push('…');
        }
        LlmError::Redirect {
            url: url.into(),
            status,
            location,
        }
    }

    /// The body's `Content-Encoding` where it is not plain bytes (the request asks for none,
    /// so only a misbehaving server or proxy compresses), redacted, then shown safely and cut:
    /// a hostile server can put the `Authorization` header it got there, and a key cut first
    /// would no longer be found whole.
    fn compressed(&self, resp: &reqwest::blocking::Response) -> Option<String> {
        let v = resp.headers().get(reqwest::header::CONTENT_ENCODING)?;
        let v = String::from_utf8_lossy(v.as_bytes()).trim().to_string();
        (!v.is_empty() && !v.eq_ignore_ascii_case("identity"))
            .then(|| crate::io::name::shown(&self.redact(&v)))
    }

    fn redact_error(&self, e: LlmError) -> LlmError {
        let r = |m: String| self.redact(&m);
        match e {
            LlmError::BadReply { url, message } => LlmError::BadReply {
                url,
                message: r(message),
            },
            LlmError::Transport { url, message } => LlmError::Transport {
                url,
                message: r(message),
            },
            other => other,
        }
    }
}

fn transport_error(e: &reqwest::Error, url: &str, cfg: &HttpConfig) -> LlmError {
    if e.is_timeout() {
        LlmError::Timeout {
            url: url.into(),
            seconds: if e.is_connect() {
                cfg.connect_timeout.as_secs_f64()
            } else {
                cfg.read_timeout.as_secs_f64()
            },
            connecting: e.is_connect(),
        }
    } else if e.is_connect() {
        let causes = causes(e);
        let text = causes.join(": ").to_lowercase();
        if [
            "tls",
            "certificate",
            "corrupt message",
            "handshake",
            "alert",
        ]
        .iter()
        .any(|w| text.contains(w))
        {
            LlmError::Tls {
                url: url.into(),
                message: causes.last().cloned().unwrap_or_default(),
            }
        } else {
            LlmError::Connect { url: url.into() }
        }
    } else {
        // reqwest's Display omits the cause chain, where the useful part is.
        // The error names its URL, which the message's caller names already.
        let own = match e.url() {
            Some(u) => e.to_string().replace(&format!(" for url ({u})"), ""),
            None => e.to_string(),
        };
        let mut msg = std::iter::once(own)
            .chain(causes(e))
            .collect::<Vec<_>>()
            .join(": ");
        // hyper's words for a reply that is not HTTP/1.x, said for what they mean.
        let lower = msg.to_lowercase();
        for (words, hint) in [
            (
                "invalid http version",
                "the answer is not HTTP/1.x (it does not start with a status line such as \
                 `HTTP/1.1 200 OK`): a server that speaks TLS asked over http:// (give its URL \
                 as https://), or not an HTTP server",
            ),
            (
                "invalid http status-code",
                "the answer's status line is not valid HTTP (it must read like `HTTP/1.1 200 OK`: \
                 a three-digit code and a reason of printable characters): not an HTTP server?",
            ),
            (
                "invalid http header",
                "the answer's headers are not valid HTTP: not an HTTP server?",
            ),
            (
                "invalid content-length",
                "the answer's Content-Length header is not one whole number (missing, not \
                 digits, or given twice with different values): a broken server or a proxy \
                 between",
            ),
            (
                "message head is too large",
                "the answer's status line and headers are larger than an HTTP client reads: \
                 not an LLM server?",
            ),
        ] {
            if lower.contains(words) {
                msg = format!("{hint} ({msg})");
                break;
            }
        }
        LlmError::Transport {
            url: url.into(),
            message: msg,
        }
    }
}

/// The causes under a request's error, outermost first (its own Display omits them).
fn causes(e: &reqwest::Error) -> Vec<String> {
    let mut out = Vec::new();
    let mut src = std::error::Error::source(e);
    while let Some(s) = src {
        out.push(s.to_string());
        src = s.source();
    }
    out
}

/// The error message of a failed request's body: `{"error": {"message": ..., "code": ...}}`
/// (code a string, number or null), `{"error": "..."}`, `{"message": "..."}`, or the bare text.
pub fn error_message(body: &str) -> String {
    error_message_redacted(body, &|s| s.to_string())
}

/// [`error_message`] with `redact` applied to each text before it is cut: a message cut first
/// kept the head of a key the server echoed at the cut (`... Bearer sk-TESTKEY-a...`), which no
/// redaction afterwards recognises; and a key written with JSON escapes (`\u0073k-...`) is
/// whole only once the body is decoded, here.
pub fn error_message_redacted(body: &str, redact: &dyn Fn(&str) -> String) -> String {
    let text = body.trim();
    let short = |s: &str| {
        let s = redact(s.trim());
        let s = s.trim();
        let mut out: String = s.chars().take(300).collect();
        if s.chars().count() > 300 {
            out.push_str("...");
        }
        out.replace(['\n', '\r'], " ")
    };
    let Ok(v) = serde_json::from_str::<Value>(text) else {
        return if text.is_empty() {
            "(empty body)".into()
        } else {
            short(text)
        };
    };
    let code = |e: &Value| match &e["code"] {
        Value::String(s) => format!(" ({})", short(s)),
        Value::Number(n) => format!(" ({n})"),
        _ => String::new(),
    };
    match &v {
        Value::String(s) => short(s),
        Value::Object(o) => match o.get("error") {
            Some(Value::String(s)) => short(s),
            Some(e @ Value::Object(_)) => match e["message"].as_str() {
                Some(m) => format!("{}{}", short(m), code(e)),
                None => short(&e.to_string()),
            },
            _ => match o.get("message").and_then(Value::as_str) {
                Some(m) => short(m),
                None => short(text),
            },
        },
        _ => short(text),
    }
}

/// What a reply the server's content filter stopped (`finish_reason: "content_filter"`) is
/// called: the model's words were withheld, so sending them back to it as an unusable reply
/// ("no ```rhai block") would blame it and ask again for what the filter stops.
pub fn content_filtered(chars: usize) -> String {
    let kept = match chars {
        0 => "nothing of it came".to_string(),
        n => format!("{n} characters of it came"),
    };
    format!(
        "the server's content filter stopped the reply (finish_reason \"content_filter\"); \
         {kept}: `drivescript ask --resume DIR` asks again (where the filter stops every answer, \
         reword the request or use a model or deployment without that filter)"
    )
}

/// What a successful reply body says.
#[derive(Debug, Clone, PartialEq)]
struct Completion {
    /// The first choice's text.
    content: String,
    usage: Option<Usage>,
    /// The token limit cut it off.
    truncated: bool,
    /// `system_fingerprint`, which tells some servers apart (Ollama's is `fp_ollama`).
    fingerprint: Option<String>,
    /// It came as a stream of events.
    streamed: bool,
}

/// [`parse_completion_redacted`] redacting nothing.
#[cfg(test)]
fn parse_completion(text: &str, url: &str) -> Result<Completion, LlmError> {
    parse_completion_redacted(text, url, &|s| s.to_string())
}

/// The first choice's text, the usage and whether the token limit cut it off, of a successful
/// reply body; `redact` is applied to what the server wrote (a refusal, a tool's name) before
/// any of it is cut into a message.
fn parse_completion_redacted(
    text: &str,
    url: &str,
    redact: &dyn Fn(&str) -> String,
) -> Result<Completion, LlmError> {
    let bad = |why: String| LlmError::BadReply {
        url: url.into(),
        message: why,
    };
    // JSON's own rule lets a reader ignore a byte order mark, which some gateways send.
    let text = text.trim_start_matches('\u{feff}');
    let v: Value = crate::io::json::parse_json(text).map_err(|e| {
        let head: String = text.trim().chars().take(120).collect();
        bad(if e.is_data() {
            format!("the reply holds {e}, so which answer it gives is unclear; it begins {head:?}")
        } else {
            format!("the reply is not JSON ({e}); it begins {head:?}")
        })
    })?;
    // Some servers (and proxies) answer an overloaded or refused request with HTTP 200 and
    // an error body: "the reply has no choices array" hid what the server said.
    if v.get("error").is_some_and(|e| !e.is_null()) && v.get("choices").is_none() {
        return Err(bad(format!(
            "the server answered HTTP 200 with an error and no completion: {}",
            error_message(text)
        )));
    }
    let choices = v["choices"]
        .as_array()
        .ok_or_else(|| bad("the reply has no \"choices\" array".into()))?;
    if choices.is_empty() {
        return Err(bad("the reply's \"choices\" is empty".into()));
    }
    // The choice of index 0 (one with none is taken for it), as a stream's is: the first in
    // the list was taken, so a reply holding only a second choice (`"index": 1`), or listing
    // it first, gave another answer than the one asked for.
    let first = super::stream::answer_choice(Some(choices), redact)
        .map_err(|m| bad(format!("the reply's {m}")))?
        .ok_or_else(|| {
            let indices: Vec<String> = choices
                .iter()
                .take(8)
                .map(|c| redact(&crate::io::name::shown_counted(&c["index"].to_string())))
                .collect();
            bad(format!(
                "the reply's \"choices\" hold no choice of index 0, the answer asked for \
                 (indices {})",
                indices.join(", ")
            ))
        })?;
    let message = &first["message"];
    // A refusal or a tool call carries no text; the model's words say why, and were dropped
    // ("no message content (a refusal or a tool call?)", or an empty reply asked for again).
    let mut tools = Vec::new();
    super::stream::tool_names(message, &mut tools);
    let tool_finish = matches!(
        first["finish_reason"].as_str(),
        Some("tool_calls" | "function_call")
    );
    let no_text = || {
        super::stream::no_text_error(
            url,
            &super::stream::refusal_text(message),
            &tools,
            tool_finish,
            redact,
        )
    };
    if first["finish_reason"].as_str() == Some("content_filter") {
        let chars =
            super::stream::content_text(&message["content"]).map_or(0, |t| t.chars().count());
        return Err(bad(content_filtered(chars)));
    }
    // Some servers return content parts (text, and refusals).
    let text = super::stream::content_text(&message["content"])
        .or_else(|| first["text"].as_str().map(str::to_string));
    if text.as_deref().is_none_or(|t| t.trim().is_empty()) {
        if let Some(e) = no_text() {
            return Err(e);
        }
    }
    let content = match text {
        Some(s) => s,
        // A reasoning model that spent the whole token limit thinking sends no content
        // (its thoughts go in `reasoning_content`): that is a reply cut off at the limit,
        // as a stream of the same reply is, which the user can fix with --max-tokens; it
        // was called "a refusal or a tool call" and ended the run.
        None if first["finish_reason"].as_str() == Some("length") => String::new(),
        None => {
            let got: String = message["content"].to_string().chars().take(60).collect();
            return Err(bad(format!(
                "the first choice has no message content: `content` is {got}, not text, and \
                 the message holds no refusal or tool call"
            )));
        }
    };
    let usage = v
        .get("usage")
        .and_then(|u| serde_json::from_value::<Usage>(u.clone()).ok());
    Ok(Completion {
        content,
        usage,
        truncated: first["finish_reason"].as_str() == Some("length"),
        fingerprint: v["system_fingerprint"].as_str().map(str::to_string),
        streamed: false,
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_token_limit_field_is_a_json_name_no_other_setting_uses() {
        for ok in [
            "max_tokens",
            "max_completion_tokens",
            "n_predict",
            "maxTokens2",
        ] {
            assert!(check_max_tokens_field(ok).is_ok(), "{ok}");
        }
        // "x y" went into the body as a field no server reads; "model" replaced the model.
        for (bad, why) in [
            ("x y", "ASCII letters, digits and `_`"),
            ("", "1 to 64 characters"),
            ("max-tokens", "ASCII letters"),
            ("tökens", "ASCII letters"),
            ("model", "already sends"),
            ("stream", "already sends"),
        ] {
            let e = check_max_tokens_field(bad).unwrap_err().to_string();
            assert!(
                e.contains("--max-tokens-field") && e.contains(why),
                "{bad:?}: {e}"
            );
        }
        let mut cfg = HttpConfig::new("http://127.0.0.1:1/v1", "m");
        cfg.max_tokens_field = "x y".into();
        assert!(HttpClient::new(cfg).is_err());
    }

    #[test]
    fn the_key_is_redacted_wherever_it_appears_but_short_keys_do_not_garble_text() {
        let k = Some("sk-abcdef123");
        assert_eq!(
            redact_key("Bearer sk-abcdef123 and sk-abcdef123", k),
            "Bearer [redacted] and [redacted]"
        );
        assert_eq!(redact_key("the cutter", Some("the")), "the cutter");
        // Wrapped or spaced by the server: still the key.
        let k = Some("sk-TEST123xyz");
        assert_eq!(
            redact_key("your key sk-TES\nT123xyz was wrong", k),
            "your key [redacted] was wrong"
        );
        assert_eq!(
            redact_key("a sk-TEST\r\n 123 xyz b sk-TEST12", k),
            "a [redacted] b sk-TEST12"
        );
        assert_eq!(redact_key("sk-TEST123xyz", k), "[redacted]");
        assert_eq!(
            redact_key("full SK-TEST123XYZ and sk-test123xyz", k),
            "full [redacted] and [redacted]"
        );
        assert_eq!(redact_key("no key", None), "no key");
    }

    #[test]
    fn error_bodies_in_every_shape_become_one_line() {
        assert_eq!(
            error_message(
                r#"{"error": {"message": "model not found", "code": "model_not_found"}}"#
            ),
            "model not found (model_not_found)"
        );
        assert_eq!(
            error_message(r#"{"error": {"message": "slow down", "code": 429}}"#),
            "slow down (429)"
        );
        assert_eq!(
            error_message(r#"{"error": {"message": "x", "code": null}}"#),
            "x"
        );
        assert_eq!(error_message(r#"{"error": "overloaded"}"#), "overloaded");
        assert_eq!(error_message(r#""bare json string""#), "bare json string");
        assert_eq!(error_message("Bad Gateway\n"), "Bad Gateway");
        assert_eq!(error_message(""), "(empty body)");
        assert_eq!(error_message(r#"{"message": "m"}"#), "m");
        assert!(error_message(&"x".repeat(1000)).ends_with("..."));
    }

    #[test]
    fn completions_parse_and_bad_replies_say_why() {
        let ok = r#"{"choices":[{"message":{"role":"assistant","content":"hi"}}],"usage":{"prompt_tokens":5,"completion_tokens":2,"total_tokens":7}}"#;
        let got = parse_completion(ok, "u").unwrap();
        assert!(!got.truncated);
        assert_eq!(
            (got.content.as_str(), got.usage),
            (
                "hi",
                Some(Usage {
                    prompt_tokens: 5,
                    completion_tokens: 2
                })
            )
        );
        let e = parse_completion("<html>oops</html>", "u").unwrap_err();
        assert!(e.to_string().contains("not JSON"), "{e}");
        // Only a second choice, or the second listed first: another answer was taken.
        let e = parse_completion(
            r#"{"choices":[{"index":1,"message":{"role":"assistant","content":"other"}}]}"#,
            "u",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("no choice of index 0") && e.contains("(indices 1)"),
            "{e}"
        );
        let two = r#"{"choices":[{"index":1,"message":{"content":"other"}},{"index":0,"message":{"content":"asked"}}]}"#;
        assert_eq!(parse_completion(two, "u").unwrap().content, "asked");
        // An index that is no whole number from 0 was taken for 0, and its text for the
        // answer; two of index 0 gave the first listed.
        for index in ["-1", "\"0\"", "1.0", "{}"] {
            let r =
                format!(r#"{{"choices":[{{"index":{index},"message":{{"content":"other"}}}}]}}"#);
            let e = parse_completion(&r, "u").unwrap_err().to_string();
            assert!(
                e.contains(&format!(
                    "the reply's choice has \"index\" {index}, not a whole number from 0"
                )),
                "{e}"
            );
        }
        let both =
            r#"{"choices":[{"index":0,"message":{"content":"a"}},{"message":{"content":"b"}}]}"#;
        let e = parse_completion(both, "u").unwrap_err().to_string();
        assert!(e.contains("two choices of index 0"), "{e}");
        let e = parse_completion(r#"{"choices": []}"#, "u").unwrap_err();
        assert!(e.to_string().contains("empty"), "{e}");
        let e = parse_completion(r#"{"id": 1}"#, "u").unwrap_err();
        assert!(e.to_string().contains("no \"choices\""), "{e}");
    }

    #[test]
    fn an_error_in_a_200_reply_and_a_reply_of_only_reasoning_cut_at_the_limit_say_so() {
        // Said "the reply has no \"choices\" array", not what the server said.
        let e = parse_completion(
            r#"{"error": {"message": "model is overloaded", "code": 503}}"#,
            "u",
        )
        .unwrap_err()
        .to_string();
        assert!(
            e.contains("HTTP 200 with an error") && e.contains("model is overloaded (503)"),
            "{e}"
        );
        // Said "no message content (a refusal or a tool call?)" and ended the run.
        let got = parse_completion(
            r#"{"choices":[{"message":{"content":null,"reasoning_content":"hmm"},"finish_reason":"length"}]}"#,
            "u",
        )
        .unwrap();
        assert!(got.truncated && got.content.is_empty());
        let e = parse_completion(r#"{"choices":[{"message":{"content":null}}]}"#, "u")
            .unwrap_err()
            .to_string();
        assert!(e.contains("no message content"), "{e}");
    }

    #[test]
    fn urls_lose_credentials_and_gain_the_endpoint() {
        assert_eq!(
            redact_url("https://user:secret@host:8080/v1?key=abc"),
            "https://host:8080/v1"
        );
        assert_eq!(
            redact_url("http://127.0.0.1:11434/v1"),
            "http://127.0.0.1:11434/v1"
        );
        let c = HttpConfig::new("http://h/v1/", "m");
        assert_eq!(c.endpoint(), "http://h/v1/chat/completions");
        let c = HttpConfig::new("http://h/v1/chat/completions", "m");
        assert_eq!(c.endpoint(), "http://h/v1/chat/completions");
        let mut c = HttpConfig::new("http://h/v1", "m");
        c.key = Some("sk-secret".into());
        assert!(!format!("{c:?}").contains("sk-secret"));
    }

    #[test]
    fn urls_lose_credentials_however_they_are_spelled() {
        // A query after the host alone, a password holding a `/`, no scheme, a fragment.
        assert_eq!(redact_url("http://h:1?key=sk-q"), "http://h:1");
        assert_eq!(redact_url("http://u:p/sk-pw@h:1/v1"), "http://h:1/v1");
        assert_eq!(redact_url("u:sk-pw@h:1/v1"), "h:1/v1");
        assert_eq!(redact_url("https://h/v1#sk-frag"), "https://h/v1");
    }

    #[test]
    fn the_endpoint_keeps_a_query_after_the_path() {
        let c = HttpConfig::new("http://h:1?key=k", "m");
        assert_eq!(c.endpoint(), "http://h:1/chat/completions?key=k");
        let c = HttpConfig::new("https://h/openai/v1/?api-version=2024-06-01", "m");
        assert_eq!(
            c.endpoint(),
            "https://h/openai/v1/chat/completions?api-version=2024-06-01"
        );
    }

    #[test]
    fn a_url_without_its_host_is_named_so_not_read_as_the_host_of_its_path() {
        // `http:///v1` connected to host "v1" (the URL standard skips the extra slash).
        for url in [
            "http:///v1",
            "http:v1",
            "https:\\\\h/v1",
            "http:////h/v1",
            " http:///v1",
        ] {
            let e = HttpClient::new(HttpConfig::new(url, "m"))
                .err()
                .expect(url)
                .to_string();
            assert!(e.contains("names no host"), "{url}: {e}");
        }
        for url in ["http://h/v1", "HTTP://h:1/v1", " http://127.0.0.1:9/v1 "] {
            assert!(HttpClient::new(HttpConfig::new(url, "m")).is_ok(), "{url}");
        }
    }

    #[test]
    fn urls_and_keys_no_request_can_carry_are_refused_without_their_secrets() {
        for url in [
            "ftp://u:sk-pw-123@h/v1",
            "u:sk-pw-123@h:1/v1",
            "http://u:p/sk-pw-123@h:1/v1",
            "h:1",
        ] {
            let e = HttpClient::new(HttpConfig::new(url, "m"))
                .err()
                .expect(url)
                .to_string();
            assert!(e.contains("--llm-url"), "{url}: {e}");
            assert!(!e.contains("sk-pw-123"), "{url}: {e}");
        }
        let mut c = HttpConfig::new("http://h/v1", "m");
        c.key = Some("sk-abc\ndef".into());
        let e = HttpClient::new(c)
            .err()
            .expect("a key with a line break")
            .to_string();
        assert!(
            e.contains("DRIVESCRIPT_LLM_KEY") && e.contains("control"),
            "{e}"
        );
        assert!(!e.contains("sk-abc"), "{e}");
        let mut c = HttpConfig::new("http://h/v1", "m");
        c.key = Some("sk-\u{fc}\u{fc}12345678".into());
        let e = HttpClient::new(c)
            .err()
            .expect("a key outside ASCII")
            .to_string();
        assert!(
            e.contains("DRIVESCRIPT_LLM_KEY") && e.contains("outside ASCII"),
            "{e}"
        );
        assert!(!e.contains("12345678"), "{e}");
    }

    #[test]
    fn what_the_url_sends_is_redacted_from_what_comes_back() {
        let c = HttpClient::new(HttpConfig::new(
            "http://u:pw-url-secret-1@h/v1?key=sk-query%2Dsecret",
            "m",
        ))
        .unwrap();
        let echoed = "Authorization: Basic dTpwdy11cmwtc2VjcmV0LTE=; password pw-url-secret-1; \
                      query sk-query%2Dsecret, decoded sk-query-secret";
        let r = c.redact(echoed);
        for secret in ["dTpwdy11cmwtc2VjcmV0LTE=", "pw-url-secret-1", "sk-query"] {
            assert!(!r.contains(secret), "{r}");
        }
        assert_eq!(base64(b"u:pw-url-secret-1"), "dTpwdy11cmwtc2VjcmV0LTE=");
        assert_eq!(base64(b"ab"), "YWI=");
        assert_eq!(base64(b"a"), "YQ==");
    }

    #[test]
    fn a_key_echoed_as_entities_escapes_base64_or_with_invisible_characters_is_redacted() {
        let key = "sk-TEST123xyz";
        let mut cfg = HttpConfig::new("http://h/v1", "m");
        cfg.key = Some(key.into());
        let c = HttpClient::new(cfg).unwrap();
        let entities: String = key.chars().map(|ch| format!("&#{};", ch as u32)).collect();
        let hex_entities: String = key
            .chars()
            .map(|ch| format!("&#x{:X};", ch as u32))
            .collect();
        let json: String = key
            .chars()
            .map(|ch| format!("\\u{:04x}", ch as u32))
            .collect();
        let zero_width: String = key.chars().flat_map(|ch| [ch, '\u{200b}']).collect();
        let mixed = "sk-&#84;E%53T\\x31\u{feff}23\u{ad}xyz";
        // HTML-escaped twice or thrice, and percent-encoded twice.
        let twice: String = key
            .chars()
            .map(|ch| format!("&amp;#{};", ch as u32))
            .collect();
        let thrice: String = key
            .chars()
            .map(|ch| format!("&AMP;amp;#x{:x};", ch as u32))
            .collect();
        let percent_twice: String = key.bytes().map(|b| format!("%25{b:02X}")).collect();
        let header = format!("Authorization: Bearer {key}");
        let mut echoes = vec![
            entities,
            hex_entities,
            json,
            zero_width,
            mixed.to_string(),
            twice,
            thrice,
            percent_twice,
        ];
        // The header block base64-encoded at each of the three alignments, and the token alone.
        for prefix in ["", "x", "xy"] {
            echoes.push(base64(format!("{prefix}{header}").as_bytes()));
        }
        echoes.push(base64(format!("Bearer {key}").as_bytes()));
        echoes.push(base64(key.as_bytes()).replace('+', "-").replace('/', "_"));
        for echoed in echoes {
            let r = c.redact(&format!("the server said: {echoed} (end)"));
            assert!(
                r.contains("[redacted]") && r.ends_with(" (end)"),
                "{echoed} -> {r}"
            );
            // What is left of the key is at most two characters of the key's ends.
            for window in key.as_bytes().windows(4) {
                let w = std::str::from_utf8(window).unwrap();
                assert!(!r.contains(w), "{echoed} -> {r}");
            }
            let decoded_left: String = r.chars().filter(|c| c.is_ascii_alphanumeric()).collect();
            assert!(!decoded_left.contains("TEST123"), "{echoed} -> {r}");
        }
        // Escapes that stand for other characters, and text near the key, are left alone.
        for plain in [
            "50%25 off &#65;&#66; \\u0041 &amp; &amp;#66; &plus; %2541",
            "sk-TEST12 is not the key",
        ] {
            assert_eq!(c.redact(plain), plain);
        }
    }

    #[test]
    fn a_key_echoed_percent_encoded_is_redacted() {
        let mut cfg = HttpConfig::new("http://h/v1", "m");
        cfg.key = Some("Zm9v+YmFy/cXV4=sk".into());
        let c = HttpClient::new(cfg).unwrap();
        for echoed in [
            "bad auth header: Bearer%20Zm9v%2BYmFy%2FcXV4%3Dsk",
            "bad auth header: Bearer%20Zm9v%2bYmFy%2fcXV4%3dsk",
            "bad auth header: Bearer Zm9v+YmFy/cXV4=sk",
        ] {
            let r = c.redact(echoed);
            assert!(!r.contains("Zm9v") && r.contains("[redacted]"), "{r}");
        }
        // Its `+`, `/` and `=` as named HTML entities, and the base64 of its percent-encoded
        // form at each alignment (a server base64-encoding the URL or form body it echoes).
        let mut echoes = vec!["Zm9v&plus;YmFy&sol;cXV4&equals;sk".to_string()];
        for prefix in ["", "x", "xy"] {
            for encoded in ["Zm9v%2BYmFy%2FcXV4%3Dsk", "Zm9v%2bYmFy%2fcXV4%3dsk"] {
                echoes.push(base64(format!("{prefix}key={encoded}").as_bytes()));
            }
        }
        for echoed in echoes {
            let r = c.redact(&format!("echo: {echoed} (end)"));
            assert!(
                r.contains("[redacted]") && r.ends_with(" (end)"),
                "{echoed} -> {r}"
            );
            // Nothing of the base64 that only the key decides is left.
            let blob = base64(b"key=Zm9v%2BYmFy%2FcXV4%3Dsk");
            assert!(!r.contains(&blob[8..20]), "{echoed} -> {r}");
        }
        // A key of unreserved characters only is the same encoded: no percent-encoded entry.
        let mut cfg = HttpConfig::new("http://h/v1", "m");
        cfg.key = Some("sk-abc_DEF.123~x".into());
        let secrets = HttpClient::new(cfg).unwrap().secrets;
        assert!(!secrets.iter().any(|s| s.contains('%')), "{secrets:?}");
    }

    #[test]
    fn the_body_always_carries_temperature_and_the_chosen_token_field() {
        let mut cfg = HttpConfig::new("http://h/v1", "m");
        cfg.max_tokens_field = "max_completion_tokens".into();
        cfg.seed = Some(7);
        let c = HttpClient::new(cfg).unwrap();
        let b = c.body(&[Message::new("user", "x")]);
        assert_eq!(b["temperature"], 0.2);
        assert_eq!(b["max_completion_tokens"], 4096);
        assert!(b.get("max_tokens").is_none());
        assert_eq!(b["seed"], 7);
        assert_eq!(b["messages"][0]["role"], "user");
    }
}
