//! A model's reply: its reasoning and either one ```rhai block (a script) or `ACCEPT`.

/// What a reply says.
#[derive(Debug, Clone, PartialEq)]
pub enum Reply {
    /// A (new or repaired) script.
    Script {
        /// The text outside the code block: the chain of thought's result.
        reasoning: String,
        /// The script.
        source: String,
    },
    /// The samples do what was asked.
    Accept {
        /// Why, in the model's words.
        reasoning: String,
    },
}

/// Why a reply cannot be used; the message goes back to the model.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum ReplyError {
    /// Nothing but whitespace: a server that sent an empty completion, or an empty file.
    #[error(
        "the reply is empty: send the whole script in one ```rhai block, or the single word \
         ACCEPT on its own line"
    )]
    Blank,
    /// Neither a code block nor ACCEPT.
    #[error(
        "the reply has no ```rhai code block and does not ACCEPT: send the whole script in one \
         ```rhai block, or the single word ACCEPT on its own line"
    )]
    NoScript,
    /// More than one candidate block.
    #[error("the reply has {0} ```rhai code blocks: send the whole script in exactly one block")]
    Several(usize),
    /// A block that never closes.
    #[error("the reply's ```rhai block starting on line {0} is never closed with ```")]
    Unclosed(usize),
    /// An empty block.
    #[error("the reply's ```rhai block is empty")]
    Empty,
}

/// Parses a reply. A script is the one block tagged `rhai`; where there is none, a single
/// untagged block is taken (models forget the tag). `ACCEPT` counts when it stands on a line
/// of its own (markdown emphasis allowed) and the reply carries no script.
pub fn parse_reply(text: &str) -> Result<Reply, ReplyError> {
    // An empty completion was said to have "no ```rhai code block", as if the model had
    // written something else.
    if text.trim().is_empty() {
        return Err(ReplyError::Blank);
    }
    let mut blocks: Vec<(String, String)> = Vec::new(); // (tag, body)
    let mut outside = String::new();
    // (line, tag, body, fence). Markdown fences a block with ``` or ~~~ (some models and
    // chat UIs write the latter); a ~~~rhai block was "no ```rhai code block".
    let mut open: Option<(usize, String, String, &str)> = None;
    for (i, line) in text.lines().enumerate() {
        let t = line.trim_start();
        match &mut open {
            None => {
                if let Some((fence, rest)) = ["```", "~~~"]
                    .iter()
                    .find_map(|f| t.strip_prefix(f).map(|r| (*f, r)))
                {
                    open = Some((
                        i + 1,
                        rest.trim().to_ascii_lowercase(),
                        String::new(),
                        fence,
                    ));
                } else {
                    outside.push_str(line);
                    outside.push('\n');
                }
            }
            Some((_, tag, body, fence)) => {
                if t.trim_end() == *fence {
                    blocks.push((std::mem::take(tag), std::mem::take(body)));
                    open = None;
                } else {
                    body.push_str(line);
                    body.push('\n');
                }
            }
        }
    }
    let reasoning = outside.trim().to_string();
    let rhai: Vec<&(String, String)> = blocks.iter().filter(|(t, _)| t == "rhai").collect();
    let chosen = match rhai.len() {
        1 => Some(rhai[0]),
        0 => {
            let untagged: Vec<&(String, String)> =
                blocks.iter().filter(|(t, _)| t.is_empty()).collect();
            (untagged.len() == 1).then(|| untagged[0])
        }
        n => return Err(ReplyError::Several(n)),
    };
    if let Some((_, body)) = chosen {
        if body.trim().is_empty() {
            return Err(ReplyError::Empty);
        }
        return Ok(Reply::Script {
            reasoning,
            source: body.clone(),
        });
    }
    if let Some((line, tag, _, _)) = open {
        if tag == "rhai" || tag.is_empty() {
            return Err(ReplyError::Unclosed(line));
        }
    }
    let accepts = reasoning.lines().any(|l| {
        let w = l
            .trim()
            .trim_matches(|c: char| c == '*' || c == '_' || c == '#' || c == '`');
        let w = w.trim().trim_end_matches(['.', '!']);
        w == "ACCEPT" || w.starts_with("ACCEPT:") || w.starts_with("ACCEPT -")
    });
    if accepts {
        Ok(Reply::Accept { reasoning })
    } else {
        Err(ReplyError::NoScript)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn an_empty_reply_is_called_empty() {
        for text in ["", " \n\t\n"] {
            assert_eq!(parse_reply(text), Err(ReplyError::Blank));
        }
        assert!(ReplyError::Blank
            .to_string()
            .starts_with("the reply is empty"));
        assert_eq!(parse_reply("hello"), Err(ReplyError::NoScript));
    }

    #[test]
    fn a_block_fenced_with_tildes_is_read_as_one_fenced_with_backticks() {
        // "the reply has no ```rhai code block" for a valid Markdown fence.
        let r = parse_reply("Plan.\n~~~rhai\nterm(\"x\", agent(1).x.last());\n~~~\n").unwrap();
        assert_eq!(
            r,
            Reply::Script {
                reasoning: "Plan.".into(),
                source: "term(\"x\", agent(1).x.last());\n".into(),
            }
        );
        // A fence closes only with its own kind: ``` inside a ~~~ block is text.
        let r = parse_reply("~~~rhai\nlet s = \"```\";\n```\n~~~\n").unwrap();
        assert!(matches!(r, Reply::Script { source, .. } if source == "let s = \"```\";\n```\n"));
        assert_eq!(
            parse_reply("~~~rhai\nlet a = 1;\n"),
            Err(ReplyError::Unclosed(1))
        );
    }

    #[test]
    fn a_script_block_with_its_reasoning() {
        let r = parse_reply(
            "Events: one.\n\n```rhai\nlet a = agent(1);\nterm(\"x\", 0.0);\n```\nDone.",
        )
        .unwrap();
        assert_eq!(
            r,
            Reply::Script {
                reasoning: "Events: one.\n\nDone.".into(),
                source: "let a = agent(1);\nterm(\"x\", 0.0);\n".into()
            }
        );
    }

    #[test]
    fn accept_alone_on_a_line_and_not_inside_words() {
        assert!(matches!(
            parse_reply("The cut-in happens.\n**ACCEPT**").unwrap(),
            Reply::Accept { .. }
        ));
        assert!(matches!(
            parse_reply("ACCEPT: all terms are zero").unwrap(),
            Reply::Accept { .. }
        ));
        assert_eq!(
            parse_reply("I cannot ACCEPT this yet").unwrap_err(),
            ReplyError::NoScript
        );
        // A script wins over a stray ACCEPT: the model is still repairing.
        assert!(matches!(
            parse_reply("ACCEPT\n```rhai\nterm(\"x\", 0.0);\n```").unwrap(),
            Reply::Script { .. }
        ));
    }

    #[test]
    fn unusable_replies_say_what_to_send() {
        assert_eq!(parse_reply("just words").unwrap_err(), ReplyError::NoScript);
        assert_eq!(
            parse_reply("```rhai\na\n```\n```rhai\nb\n```").unwrap_err(),
            ReplyError::Several(2)
        );
        assert_eq!(
            parse_reply("text\n```rhai\nlet a = 1;").unwrap_err(),
            ReplyError::Unclosed(2)
        );
        assert_eq!(
            parse_reply("```rhai\n\n```").unwrap_err(),
            ReplyError::Empty
        );
        // One untagged block is taken; a python block is not a script.
        assert!(matches!(
            parse_reply("```\nterm(\"x\", 0.0);\n```").unwrap(),
            Reply::Script { .. }
        ));
        assert_eq!(
            parse_reply("```python\nprint(1)\n```").unwrap_err(),
            ReplyError::NoScript
        );
        assert!(ReplyError::NoScript.to_string().contains("ACCEPT"));
    }
}
