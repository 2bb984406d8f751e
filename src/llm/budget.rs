//! The context budget: how many tokens a request takes, and whether the server saw all of it.
//!
//! Local servers cut prompts to their context window without an error (Ollama's
//! OpenAI-compatible endpoint keeps the last 2,048 or 4,096 tokens by default and ignores a
//! `num_ctx` in the request), and the model then answers a prompt without its rules, reference
//! or request. The reply's `usage.prompt_tokens` shows it: a prompt that came back much shorter
//! than the one sent was cut, and the run stops with the fix for the server in use.

use super::client::Message;

/// Characters per token assumed by [`estimate_tokens`]. Tokenizers of current models take 3.5
/// to 4.5 characters of English prose per token and fewer of code and numbers; 3 errs on the
/// side of more tokens, so that a conversation fitted to a window fits it.
pub const CHARS_PER_TOKEN: f64 = 3.0;

/// Tokens a chat template adds around each message (role markers, separators).
pub const TOKENS_PER_MESSAGE: u64 = 4;

/// A prompt counts as cut when the server reports fewer than this share of the estimate: well
/// below any tokenizer's count of the same text, well above what a cut to a default window
/// leaves of a first prompt.
pub const TRUNCATED_SHARE: f64 = 0.5;

/// Prompts estimated below this are not checked: no server's window is smaller, and in a
/// prompt of a few words the per-message overhead, which servers count differently, is most of
/// the estimate.
pub const MIN_CHECKED_TOKENS: u64 = 256;

/// Tokens of `text`, estimated from its length (no tokenizer is shipped: each model has its own).
pub fn estimate_text(text: &str) -> u64 {
    (text.chars().count() as f64 / CHARS_PER_TOKEN).ceil() as u64
}

/// Tokens of a request's messages, estimated.
pub fn estimate_tokens(messages: &[Message]) -> u64 {
    messages
        .iter()
        .map(|m| estimate_text(&m.content) + TOKENS_PER_MESSAGE)
        .sum()
}

/// The kinds of server whose context settings differ.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ServerKind {
    /// Ollama (`/v1` on port 11434; its replies carry `system_fingerprint: fp_ollama`).
    Ollama,
    /// llama.cpp's `llama-server` (port 8080), or llama-cpp-python's server.
    LlamaCpp,
    /// vLLM (port 8000).
    Vllm,
    /// LM Studio (port 1234).
    LmStudio,
    /// Any other.
    Unknown,
}

impl ServerKind {
    /// The kind of server at `url`, by the reply's fingerprint where it has one, else by the
    /// port each server listens on by default.
    pub fn detect(url: &str, fingerprint: Option<&str>) -> Self {
        if fingerprint.is_some_and(|f| f.contains("ollama")) || url.contains("ollama") {
            return Self::Ollama;
        }
        let port = url
            .split_once("://")
            .map_or(url, |(_, r)| r)
            .split('/')
            .next()
            .and_then(|host| host.rsplit_once(':'))
            .and_then(|(_, p)| p.parse::<u16>().ok());
        match port {
            Some(11434) => Self::Ollama,
            Some(8080) => Self::LlamaCpp,
            Some(8000) => Self::Vllm,
            Some(1234) => Self::LmStudio,
            _ => Self::Unknown,
        }
    }

    /// How to give this server a context window of `tokens`.
    pub fn fix(self, tokens: u64) -> String {
        let ollama = format!(
            "Ollama: start it with `OLLAMA_CONTEXT_LENGTH={tokens} ollama serve`, or create a \
             model whose Modelfile says `PARAMETER num_ctx {tokens}` (`ollama create`) and ask \
             for that model (its /v1 endpoint, the one ask speaks, ignores num_ctx in the \
             request)"
        );
        let llama = format!(
            "llama.cpp: start `llama-server` with `--ctx-size {tokens}` (llama-cpp-python: \
             `--n_ctx {tokens}`)"
        );
        let vllm = format!("vLLM: start `vllm serve` with `--max-model-len {tokens}`");
        let lms = format!("LM Studio: load the model with a context length of {tokens}");
        match self {
            Self::Ollama => ollama,
            Self::LlamaCpp => llama,
            Self::Vllm => vllm,
            Self::LmStudio => lms,
            Self::Unknown => format!("{ollama}; {llama}; {vllm}; {lms}"),
        }
    }
}

/// The window to ask a server for: room for the prompt and the reply, rounded up to a power
/// of two (the sizes servers and model cards use).
pub fn window_for(prompt: u64, reply: u64) -> u64 {
    (prompt + reply).max(1).next_power_of_two()
}

/// Whether the server saw the whole prompt: `reported` prompt tokens against the `estimate`
/// sent. `None` when it did, else the message saying it was cut and how to fix it. A count of
/// 0 is a server that does not count (proxies and servers that fill `usage` with zeros): no
/// window holds no token of a prompt, and `ask` failed on every reply of such a server, telling
/// the user to enlarge a context window that was not the matter.
pub fn check_prompt_tokens(
    estimate: u64,
    reported: u64,
    reply_tokens: u64,
    kind: ServerKind,
) -> Option<String> {
    if reported == 0
        || estimate < MIN_CHECKED_TOKENS
        || (reported as f64) >= TRUNCATED_SHARE * estimate as f64
    {
        return None;
    }
    Some(format!(
        "the server read {reported} tokens of a prompt of about {estimate}: it cut the prompt to \
         its context window without an error, so the model never saw the rest (the rules, the \
         reference or the request). Give it a window of at least {} tokens: {}; or, where the model's \
         window is smaller, start the run with --context N, and it fits the conversation into it \
         (a run taken up with --resume or --continue keeps the window it started with)",
        window_for(estimate, reply_tokens),
        kind.fix(window_for(estimate, reply_tokens))
    ))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn servers_are_told_apart_by_fingerprint_and_port() {
        assert_eq!(
            ServerKind::detect("http://box:9999/v1", Some("fp_ollama")),
            ServerKind::Ollama
        );
        assert_eq!(
            ServerKind::detect("http://127.0.0.1:11434/v1", None),
            ServerKind::Ollama
        );
        assert_eq!(
            ServerKind::detect("http://u:p@127.0.0.1:8080/v1", None),
            ServerKind::LlamaCpp
        );
        assert_eq!(ServerKind::detect("http://h:8000", None), ServerKind::Vllm);
        assert_eq!(
            ServerKind::detect("https://api.openai.com/v1", None),
            ServerKind::Unknown
        );
    }

    #[test]
    fn a_cut_prompt_is_named_with_the_fix_for_its_server() {
        assert_eq!(
            check_prompt_tokens(7000, 6100, 4096, ServerKind::Ollama),
            None
        );
        assert_eq!(check_prompt_tokens(10, 1, 4096, ServerKind::Ollama), None);
        // A server that fills usage with zeros counts nothing: it cut nothing either.
        assert_eq!(
            check_prompt_tokens(7000, 0, 4096, ServerKind::Unknown),
            None
        );
        let m = check_prompt_tokens(7000, 2048, 4096, ServerKind::Ollama).unwrap();
        assert!(
            m.contains("read 2048 tokens of a prompt of about 7000")
                && m.contains("OLLAMA_CONTEXT_LENGTH=16384")
                && m.contains("num_ctx 16384")
                && !m.contains("/api/chat"),
            "{m}"
        );
        let m = check_prompt_tokens(7000, 2048, 1024, ServerKind::Unknown).unwrap();
        for want in [
            "--ctx-size 8192",
            "--max-model-len 8192",
            "OLLAMA_CONTEXT_LENGTH",
        ] {
            assert!(m.contains(want), "{want}: {m}");
        }
    }

    #[test]
    fn estimates_count_characters_and_message_overhead() {
        assert_eq!(estimate_text("abcdef"), 2);
        assert_eq!(
            estimate_tokens(&[Message::new("user", "abcdefg")]),
            3 + TOKENS_PER_MESSAGE
        );
    }
}
