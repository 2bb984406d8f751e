//! The LLM in the loop: words → cost script → guided samples → repaired script.
//!
//! A [`session`] runs the paper's two modules over one run directory. High-level understanding
//! sends the system prompt ([`prompt`]: a designed chain of thought, worked examples and the
//! stdlib reference generated from the engine) and a scene summary written for a language
//! model; the reply's one ```rhai block ([`reply`]) is validated on the sampler's own horizon
//! before anything is sampled. Low-level refinement sends back, per round, the named agents'
//! trajectories, events and every term's value with its spread over the samples
//! ([`feedback`]); the model answers ACCEPT or a repaired script. Three backends answer: an
//! OpenAI-compatible server ([`client`]), a person pasting files (manual), and a deterministic
//! planner over `scripts/` ([`rules`]), which also names the independent checkers of a
//! request whatever backend writes its script.

pub mod batch;
pub mod budget;
pub mod client;
pub mod clock;
pub mod feedback;
pub mod fit;
pub mod prompt;
pub mod replay;
pub mod reply;
pub mod rules;
pub mod rundir;
pub mod session;
pub mod stream;

use std::path::PathBuf;

pub use client::{HttpClient, HttpConfig, Message};
pub use prompt::{Cot, PromptOptions, Prompts};
pub use session::{Backend, Outcome, Session, SessionConfig};

/// [`LlmError::Timeout`] in words: `--llm-timeout` bounds the silence of a reply, not the
/// connection (10 s), which it once told the user to raise.
fn timeout_words(seconds: f64, connecting: bool) -> String {
    if connecting {
        format!(
            "no connection within {seconds} s: nothing answers at that host and port (a \
             firewall, a wrong address), or the TLS handshake stalled (an https:// URL for a \
             server that speaks plain HTTP)"
        )
    } else {
        format!("no reply within {seconds} s (raise --llm-timeout for slow models)")
    }
}

/// What can go wrong in the loop.
#[derive(Debug, thiserror::Error)]
pub enum LlmError {
    /// No server listens at the URL.
    #[error(
        "cannot connect to the LLM server at {url} (connection refused or no such host): start \
         one (`ollama serve`, `vllm serve MODEL`, `llama-server -m MODEL.gguf`) or point \
         DRIVESCRIPT_LLM_URL / --llm-url at one; without a server, --llm rules plans known \
         behaviours and --llm manual lets you paste prompts into any chat"
    )]
    Connect {
        /// The endpoint, without credentials.
        url: String,
    },
    /// The connection or the reply took too long.
    #[error("{url}: {}", timeout_words(*seconds, *connecting))]
    Timeout {
        /// The endpoint.
        url: String,
        /// The limit.
        seconds: f64,
        /// Whether connecting (not reading) timed out.
        connecting: bool,
    },
    /// The TLS handshake of an `https://` URL failed: most often a server that speaks plain
    /// HTTP, or a certificate that is not trusted.
    #[error(
        "{url}: the TLS (https) handshake failed ({message}): Ollama, llama.cpp's server and \
         vLLM speak plain HTTP unless set up otherwise (give their URL as http://), and a \
         server's certificate must be trusted by this machine"
    )]
    Tls {
        /// The endpoint, without credentials.
        url: String,
        /// The TLS library's own words.
        message: String,
    },
    /// The server reset or closed the connection in the middle of the reply.
    #[error(
        "{url}: the server reset or closed the connection in the middle of the reply, after {bytes} \
         bytes ({message}); it may have crashed or run out of memory: check its log, then \
         `drivescript ask --resume DIR` asks again"
    )]
    Reset {
        /// The endpoint, without credentials.
        url: String,
        /// Bytes of the body that had arrived.
        bytes: usize,
        /// The transport's own words.
        message: String,
    },
    /// A streamed reply stopped coming, or kept coming without tokens.
    #[error(
        "{url}: the stream stalled: {} for {seconds} s after {tokens} tokens; the server may be \
         stuck or overloaded (raise --llm-timeout if the model is merely slow, or try \
         --no-stream)",
        if *keepalive { "no token came (only keep-alive comments or empty chunks)" } else { "nothing came" }
    )]
    Stalled {
        /// The endpoint, without credentials.
        url: String,
        /// The silence (or the time without a token) allowed.
        seconds: f64,
        /// Tokens received before it.
        tokens: usize,
        /// Bytes kept coming, but no token among them.
        keepalive: bool,
    },
    /// A reply, retries and the waits between them included, took longer than the deadline.
    #[error(
        "{url}: abandoned the reply after {elapsed:.1} s, past the reply deadline of {deadline} s, \
         with {received} received (raise --reply-deadline if the model is merely this slow)"
    )]
    Deadline {
        /// The endpoint, without credentials.
        url: String,
        /// Seconds since the first request.
        elapsed: f64,
        /// The deadline, seconds.
        deadline: f64,
        /// What had arrived, in words (`12 tokens`, `300 bytes of a JSON body`).
        received: String,
    },
    /// The conversation does not fit the context window `--context` states.
    #[error("{0}")]
    Context(String),
    /// The server cut the prompt to its context window.
    #[error("{url}: {message}")]
    ContextCut {
        /// The endpoint, without credentials.
        url: String,
        /// What was cut and how to give the server a larger window.
        message: String,
    },
    /// 401 or 403.
    #[error(
        "{url}: the server refused the request ({status}: {message}); check DRIVESCRIPT_LLM_KEY"
    )]
    Auth {
        /// The endpoint.
        url: String,
        /// HTTP status.
        status: u16,
        /// The server's message.
        message: String,
    },
    /// 404.
    #[error(
        "{url}: not found (404: {message}); check the model name {model:?} and that the URL \
         is the API's base (it usually ends in /v1)"
    )]
    NotFound {
        /// The endpoint.
        url: String,
        /// The model asked for.
        model: String,
        /// The server's message.
        message: String,
    },
    /// Another status, or 429/5xx on every attempt.
    #[error("{url}: HTTP {status} after {attempts} attempt(s): {message}")]
    Status {
        /// The endpoint.
        url: String,
        /// HTTP status of the last attempt.
        status: u16,
        /// Attempts made.
        attempts: u32,
        /// The server's message.
        message: String,
    },
    /// A redirect the client does not follow (another server, or one that turns the request
    /// into a GET).
    #[error(
        "{url}: the server redirects the request (HTTP {status}) to {location}; drivescript \
         follows only a 307 or 308 on the same server (a redirect elsewhere would take the \
         prompt, and the key, where the server says): if that is the LLM server, point \
         --llm-url (or DRIVESCRIPT_LLM_URL) at it"
    )]
    Redirect {
        /// The endpoint, without credentials.
        url: String,
        /// HTTP status of the redirect.
        status: u16,
        /// Where it points, without credentials or query.
        location: String,
    },
    /// A successful status with a body that is not a completion.
    #[error("{url}: unusable reply: {message}")]
    BadReply {
        /// The endpoint.
        url: String,
        /// What is wrong.
        message: String,
    },
    /// The model refused to answer (`refusal` in its message): a run gives up on it, as
    /// on any answer it cannot use, rather than asking again for the same refusal; a batch
    /// records the pair so and goes on.
    #[error("{url}: {message}")]
    Refused {
        /// The endpoint.
        url: String,
        /// The model's words, redacted and cut.
        message: String,
    },
    /// Any other transport failure.
    #[error("{url}: {message}")]
    Transport {
        /// The endpoint.
        url: String,
        /// What failed.
        message: String,
    },
    /// The client could not be built.
    #[error("{0}")]
    Setup(String),
    /// A prompt template is missing or malformed.
    #[error("prompt template {}: {message}", path.display())]
    Prompt {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The request (or a follow-up) cannot be asked: it has no words.
    #[error("{0}")]
    Request(String),
    /// The rules planner cannot plan the request.
    #[error(transparent)]
    Rules(#[from] rules::RulesError),
    /// A file or directory the loop reads or writes, other than a run directory (a batch
    /// file, a scene, a batch's output directory) is unusable.
    #[error("{}: {message}", path.display())]
    Input {
        /// The file or directory.
        path: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// The run directory as a whole cannot be used (it holds another run, another process
    /// holds it, it cannot be listed).
    #[error("run directory {}: {message}", dir.display())]
    Run {
        /// The directory.
        dir: PathBuf,
        /// What is wrong.
        message: String,
    },
    /// A file or directory inside a run directory (`state.json`, `round_3/`, a round's file)
    /// is not what the run expects there, or cannot be read or written. Named itself, not by
    /// the run directory that holds it, which is not what is wrong.
    #[error("{}: {message}", path.display())]
    RunFile {
        /// The file or directory.
        path: PathBuf,
        /// What is wrong, and what the run expects there.
        message: String,
    },
    /// A file of a run cannot be written or read (the error names the file).
    #[error(transparent)]
    Io(crate::io::IoError),
    /// Sampling failed (not a script error: those go back to the model).
    #[error(transparent)]
    Attempt(#[from] crate::sample::AttemptError),
}
