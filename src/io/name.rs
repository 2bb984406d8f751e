//! Names read from files (scenario ids, script test cases) and written by scripts (term names):
//! what may be in one. They reach terminals, reports, SVG titles and the LLM's prompt, where a
//! control character is an escape sequence or a fake `error:` line and an invisible one makes
//! `a` read as `b`, so both are refused where the name is read.

use std::fmt;

/// The longest part of a name quoted in a message, characters: a message about a bad name
/// must not itself be an essay.
pub const QUOTED_CHARS: usize = 64;

/// The longest scenario id, bytes: ids become file names (`ID_K.json`, within the 255 bytes a
/// file name may have) and are shown in tables and prompts.
pub const MAX_SCENARIO_ID_BYTES: usize = 200;

/// A character a name must not hold.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct BadChar(pub char);

impl fmt::Display for BadChar {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let kind = if self.0.is_control() {
            "control"
        } else {
            "invisible"
        };
        write!(f, "the {kind} character U+{:04X}", self.0 as u32)
    }
}

/// The first character of `s` that changes how text around it is shown without being seen:
/// bidirectional controls (which can make `a` read as `b` on a terminal), zero-width
/// characters, the byte-order mark, the soft hyphen.
pub fn hidden_char(s: &str) -> Option<char> {
    s.chars().find(|&c| is_hidden(c))
}

fn is_hidden(c: char) -> bool {
    matches!(
        c,
        '\u{00AD}'
            | '\u{061C}'
            | '\u{180E}'
            | '\u{200B}'..='\u{200F}'
            | '\u{202A}'..='\u{202E}'
            | '\u{2060}'..='\u{2064}'
            | '\u{2066}'..='\u{2069}'
            | '\u{FEFF}'
    )
}

/// Whether `c` may not be shown as it is: a control character (newlines included) or an
/// invisible one ([`hidden_char`]).
pub fn unshowable(c: char) -> bool {
    c.is_control() || is_hidden(c)
}

/// Checks a name: its first control or invisible character is the error.
pub fn check_name(name: &str) -> Result<(), BadChar> {
    match name.chars().find(|&c| unshowable(c)) {
        Some(c) => Err(BadChar(c)),
        None => Ok(()),
    }
}

/// `s` as it can be shown anywhere: every control or invisible character written as an escape
/// (`\u{202E}`), and at most [`QUOTED_CHARS`] characters of it, `…` marking a cut. For quoting
/// a name in the message that refuses it.
pub fn shown(s: &str) -> String {
    let mut out = String::new();
    for (i, c) in s.chars().enumerate() {
        if i == QUOTED_CHARS {
            out.push('…');
            break;
        }
        if unshowable(c) {
            out.push_str(&format!("\\u{{{:04X}}}", c as u32));
        } else {
            out.push(c);
        }
    }
    out
}

/// The first `k` of `names` joined by commas, with `, …` after them when there are more: for
/// naming a few of many unexpected entries (tensors, keys) in a one-line message.
pub fn first_few<S: AsRef<str>>(names: &[S], k: usize) -> String {
    let shown: Vec<&str> = names.iter().take(k).map(|n| n.as_ref()).collect();
    format!(
        "{}{}",
        shown.join(", "),
        if names.len() > k { ", …" } else { "" }
    )
}

/// [`shown`] with the length said where it cuts (`xxx… (5000 characters)`): for quoting a
/// value the user typed in the message that refuses it, so that a 5000-character flag value is
/// not echoed whole, yet the message says how long it was.
pub fn shown_counted(s: &str) -> String {
    let n = s.chars().count();
    if n > QUOTED_CHARS {
        format!("{} ({n} characters)", shown(s))
    } else {
        shown(s)
    }
}

/// `s` as a terminal can show it whatever it holds: text a server, a reply or a file wrote,
/// printed in a message or as progress. Every control character but the line break and the
/// tab (an escape sequence clears the screen, retitles the window or writes the clipboard; a
/// carriage return overwrites the line with a fake verdict) and every invisible one is written
/// as an escape (`\u{001B}`); nothing is cut.
pub fn terminal_safe(s: &str) -> String {
    if !s.chars().any(|c| unshowable(c) && c != '\n' && c != '\t') {
        return s.to_string();
    }
    let mut out = String::with_capacity(s.len() + 16);
    for c in s.chars() {
        if unshowable(c) && c != '\n' && c != '\t' {
            out.push_str(&format!("\\u{{{:04X}}}", c as u32));
        } else {
            out.push(c);
        }
    }
    out
}

/// `s` on one line, whatever it holds: every control character (the line break too) and every
/// invisible one written as an escape (`\u{000A}`), nothing cut. For a file name in a line of
/// text: a name may hold a line break or an escape sequence, and directories are walked for
/// names nobody typed.
pub fn one_line(s: &str) -> String {
    let mut out = String::with_capacity(s.len());
    for c in s.chars() {
        if unshowable(c) {
            out.push_str(&format!("\\u{{{:04X}}}", c as u32));
        } else {
            out.push(c);
        }
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn terminal_safe_text_keeps_lines_and_tabs_and_escapes_the_rest() {
        assert_eq!(terminal_safe("a\tb\nc"), "a\tb\nc");
        assert_eq!(
            terminal_safe("bad\u{1b}]52;c;eA==\u{7}\rok\u{202E}"),
            "bad\\u{001B}]52;c;eA==\\u{0007}\\u{000D}ok\\u{202E}"
        );
    }

    #[test]
    fn control_and_invisible_characters_are_named_as_escapes() {
        assert_eq!(check_name("US101-3_3_T-1 (a)"), Ok(()));
        for (name, want) in [
            ("x\ny", "the control character U+000A"),
            ("x\u{1b}[2J", "the control character U+001B"),
            ("high\u{202E}way", "the invisible character U+202E"),
            ("go\u{200B}al", "the invisible character U+200B"),
        ] {
            assert_eq!(check_name(name).unwrap_err().to_string(), want, "{name:?}");
        }
        assert_eq!(
            shown("a\u{1b}[2J\u{202E}b\nc"),
            "a\\u{001B}[2J\\u{202E}b\\u{000A}c"
        );
        let long = shown(&"x".repeat(100_000));
        assert_eq!(long.chars().count(), QUOTED_CHARS + 1);
        assert!(long.ends_with('…'));
        assert_eq!(shown_counted("a\nb"), "a\\u{000A}b");
        let long = shown_counted(&"x".repeat(5000));
        assert_eq!(
            long,
            format!("{}… (5000 characters)", "x".repeat(QUOTED_CHARS))
        );
    }
}
