//! candle's errors as users see them: with `RUST_BACKTRACE=1` candle wraps every error it makes
//! in a captured backtrace, which its message then prints (88 lines for a checkpoint whose
//! tensor shapes do not match). The message is what a user needs; the backtrace is candle's.

/// `e` without the backtraces candle wrapped around it (at any depth), its context and paths
/// kept. Where candle formatted an error with its backtrace into a new message (`VarMap::load`
/// does, for a tensor of the wrong shape), the message is cut before the backtrace's frames.
pub fn without_backtrace(e: candle_core::Error) -> candle_core::Error {
    let e = unwrapped(e);
    let text = e.to_string();
    let cut = before_frames(&text);
    if cut.len() == text.len() {
        e
    } else {
        candle_core::Error::Msg(cut.trim_end().to_string())
    }
}

fn unwrapped(e: candle_core::Error) -> candle_core::Error {
    match e {
        candle_core::Error::WithBacktrace { inner, .. } => unwrapped(*inner),
        candle_core::Error::Context { inner, context } => candle_core::Error::Context {
            inner: Box::new(unwrapped(*inner)),
            context,
        },
        candle_core::Error::WithPath { inner, path } => candle_core::Error::WithPath {
            inner: Box::new(unwrapped(*inner)),
            path,
        },
        other => other,
    }
}

/// `text` up to the first line of a printed backtrace: an indented frame number (`   0: bt`).
fn before_frames(text: &str) -> &str {
    let mut at = 0;
    for line in text.split_inclusive('\n') {
        let t = line.trim_start();
        let digits = t.bytes().take_while(u8::is_ascii_digit).count();
        if line.starts_with(' ') && digits > 0 && t[digits..].starts_with(": ") {
            return &text[..at];
        }
        at += line.len();
    }
    text
}

/// The message of `e` without candle's backtraces ([`without_backtrace`]), on one line (candle
/// puts a context on a line of its own).
pub fn message(e: candle_core::Error) -> String {
    without_backtrace(e)
        .to_string()
        .lines()
        .map(str::trim)
        .filter(|l| !l.is_empty())
        .collect::<Vec<_>>()
        .join(": ")
}

/// [`message`] for a caller that names the file itself: without the `path: "..."` candle puts
/// before an error it met reading one (the file named twice, once as Rust's debug string).
pub fn message_in_file(e: candle_core::Error) -> String {
    match unwrapped(e) {
        candle_core::Error::WithPath { inner, .. } => message(*inner),
        other => message(other),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_backtrace_is_dropped_at_any_depth_and_the_message_kept() {
        let shape = || candle_core::Error::Msg("shape mismatch in set, lhs: [2], rhs: [3]".into());
        let traced = |e: candle_core::Error| candle_core::Error::WithBacktrace {
            inner: Box::new(e),
            backtrace: Box::new(std::backtrace::Backtrace::force_capture()),
        };
        let e = traced(
            traced(shape())
                .with_path("w.safetensors")
                .context("loading"),
        );
        assert!(e.to_string().lines().count() > 3, "{e}");
        assert_eq!(
            message(e),
            "loading: path: \"w.safetensors\" shape mismatch in set, lhs: [2], rhs: [3]"
        );
        // A backtrace formatted into another error's message, as `VarMap::load` does.
        let baked = candle_core::Error::Msg(format!("error setting w: {}", traced(shape())));
        assert_eq!(
            message(baked),
            "error setting w: shape mismatch in set, lhs: [2], rhs: [3]"
        );
    }
}
