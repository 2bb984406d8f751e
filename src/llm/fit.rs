//! Fitting the conversation to the model's context window (`ask --context N`).
//!
//! The whole first prompt is about 7,000 tokens and every round adds a few thousand; a local
//! model often has 4,096. With a window stated, the first prompt gives up, in this order and
//! only as far as it must: the reference's functions that neither the prompt's rules, the
//! worked examples, nor the scripts of the behaviours the request's words name use (the
//! compact reference); agents of the scene beyond those nearest the named ones (the named
//! agents and their lanes always stay); the worked examples other than the one nearest the
//! request; the functions' explanations; that example. Later rounds keep the system prompt, the request and
//! the last exchange whole, and summarise the rounds before it. What was left out is said.

use std::collections::BTreeSet;

use super::budget::estimate_tokens;
use super::client::Message;
use super::prompt::{PromptOptions, Prompts};
use super::rules::{script_source, understand_request};
use crate::cost::{module_functions, reference, STDLIB_MODULES};
use crate::eval::behaviors::Behavior;

/// The smallest context window a run may state (`--context`).
pub const MIN_CONTEXT: u64 = 512;
/// The largest context window a run may state (`--context`).
pub const MAX_CONTEXT: u64 = 10_000_000;

/// Tokens kept for the reply out of a window of `window`: `max_tokens`, but at most a quarter
/// of the window (a reply with its reasoning and script is 500 to 1,000 tokens).
pub fn reply_budget(window: u64, max_tokens: u64) -> u64 {
    max_tokens.min(window / 4).max(1)
}

/// Messages fitted to a budget, with what was left out to fit.
#[derive(Debug, Clone, PartialEq)]
pub struct Fitted {
    /// What to send.
    pub messages: Vec<Message>,
    /// What they lack, in words (empty when nothing was left out).
    pub left_out: Vec<String>,
}

/// Identifiers a script calls (`name(`) or reads (`.name`): what its reference must document.
pub fn used_names(source: &str) -> BTreeSet<String> {
    let b = source.as_bytes();
    let mut out = BTreeSet::new();
    let mut i = 0;
    while i < b.len() {
        if b[i].is_ascii_alphabetic() || b[i] == b'_' {
            let start = i;
            while i < b.len() && (b[i].is_ascii_alphanumeric() || b[i] == b'_') {
                i += 1;
            }
            let after_dot = start > 0 && b[start - 1] == b'.';
            let called = b.get(i) == Some(&b'(');
            if after_dot || called {
                out.insert(source[start..i].to_string());
            }
        } else {
            i += 1;
        }
    }
    out
}

/// One function (or group of them) of the reference.
#[derive(Debug, Clone)]
struct Entry {
    section: String,
    signature: String,
    doc: String,
    names: BTreeSet<String>,
}

/// The whole reference as entries: the engine's natives and the stdlib modules' functions.
fn entries() -> Vec<Entry> {
    let mut out: Vec<Entry> = reference()
        .into_iter()
        .map(|d| Entry {
            section: d.section.to_string(),
            signature: d.signature.to_string(),
            doc: d.doc.to_string(),
            names: used_names(d.signature),
        })
        .collect();
    for (module, src) in STDLIB_MODULES {
        for (sig, doc) in module_functions(src) {
            out.push(Entry {
                section: format!("Module `{module}` (`import \"{module}\" as m;`, `m::f(...)`)"),
                names: used_names(&sig),
                signature: sig,
                doc,
            });
        }
    }
    out
}

/// The reference limited to the functions in `needed` (operators and entries that name no
/// function are left out: the model knows arithmetic), with or without their explanations.
/// Returns the markdown and how many entries it left out.
pub fn compact_reference(needed: &BTreeSet<String>, docs: bool) -> (String, usize) {
    let all = entries();
    let mut md = String::from(
        "Values are `Series` (one value per future step; element 0 is DT after the current \
         step), `Dual` or numbers; arithmetic mixes them. Metres, seconds, radians; `d` is \
         positive to the left. Only the functions this request needs are listed.\n",
    );
    let mut section = String::new();
    let mut kept = 0;
    for e in all
        .iter()
        .filter(|e| e.names.iter().any(|n| needed.contains(n)))
    {
        if e.section != section {
            section = e.section.clone();
            md.push_str(&format!("\n## {section}\n\n"));
        }
        kept += 1;
        if docs {
            md.push_str(&format!("- `{}`: {}\n", e.signature, e.doc));
        } else {
            md.push_str(&format!("- `{}`\n", e.signature));
        }
    }
    (md, all.len() - kept)
}

/// Words of a request and the behaviours whose scripts show the functions it needs, for
/// requests the rules planner does not read.
const WORDS: &[(&str, Behavior)] = &[
    ("cut", Behavior::CutIn),
    ("lane", Behavior::LaneChangeLeft),
    ("rightmost", Behavior::RightmostLane),
    ("road", Behavior::OffRoad),
    ("collid", Behavior::NoCollisions),
    ("crash", Behavior::Accident),
    ("accident", Behavior::Accident),
    ("speed", Behavior::SpeedLimit),
    ("slow", Behavior::SpeedLimit),
    ("fast", Behavior::SpeedLimit),
    ("stop", Behavior::Stop),
    ("follow", Behavior::Follow),
    ("yield", Behavior::Yield),
    ("revers", Behavior::Reverse),
    ("back", Behavior::Reverse),
    ("weav", Behavior::Weave),
    ("point", Behavior::TargetPoint),
    ("reach", Behavior::TargetPoint),
];

/// The behaviours a request names: the rules planner's reading where it has one, else its
/// words.
pub fn request_behaviours(request: &str) -> Vec<Behavior> {
    if let Ok(events) = understand_request(request) {
        return events.into_iter().map(|e| e.behaviour).collect();
    }
    let lower = request.to_lowercase();
    let mut out: Vec<Behavior> = Vec::new();
    for (w, b) in WORDS {
        if lower.contains(w) && !out.contains(b) {
            out.push(*b);
        }
    }
    out
}

/// The functions the request's behaviours' shipped scripts use.
pub fn request_names(requests: &[String]) -> BTreeSet<String> {
    requests
        .iter()
        .flat_map(|r| request_behaviours(r))
        .flat_map(|b| used_names(script_source(b)))
        .collect()
}

/// The code of a markdown text: its code blocks and `inline code`.
pub fn code_of(md: &str) -> String {
    let mut out = String::new();
    let mut in_block = false;
    for line in md.lines() {
        if line.trim_start().starts_with("```") {
            in_block = !in_block;
            continue;
        }
        if in_block {
            out.push_str(line);
            out.push('\n');
        } else {
            for (k, part) in line.split('`').enumerate() {
                if k % 2 == 1 {
                    out.push_str(part);
                    out.push('\n');
                }
            }
        }
    }
    out
}

/// A window and the part of it kept for the reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct Window {
    /// The model's context window, tokens.
    pub tokens: u64,
    /// Tokens kept for the reply ([`reply_budget`]).
    pub reply: u64,
}

impl Window {
    /// The tokens a prompt may take.
    pub fn prompt(&self) -> u64 {
        self.tokens.saturating_sub(self.reply)
    }
}

/// A first prompt that does not fit its window even at its smallest.
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error(
    "the first prompt takes about {smallest} tokens even with the compact reference, the named \
     agents only and no worked examples: more than the {} a window of {} leaves after {} for \
     the reply; raise --context (and the server's window) or lower --max-tokens",
    window.prompt(),
    window.tokens,
    window.reply
)]
pub struct FirstTooLarge {
    /// Tokens of the smallest first prompt.
    pub smallest: u64,
    /// The window it was fitted to.
    pub window: Window,
}

/// The first prompt's two messages within `window`: the whole prompt where it fits, else the
/// compact reference, then fewer agents, then one example, then the reference without its
/// explanations, then no example. `scene(n)` is the scene summary listing at most `n` agents; `keep` agents are
/// always listed. The error says how far the smallest prompt is over.
pub fn fit_first(
    prompts: &Prompts,
    opts: &PromptOptions,
    requests: &[String],
    scene: &dyn Fn(usize) -> String,
    max_agents: usize,
    keep: usize,
    window: Window,
) -> Result<Fitted, FirstTooLarge> {
    let request = requests.join("\n");
    let build = |examples: &[(String, String)], reference: &str, agents: usize| {
        vec![
            Message::new("system", prompts.system_with(opts, examples, reference)),
            Message::new("user", prompts.request(&scene(agents), &request)),
        ]
    };
    let all = prompts.examples();
    let whole = vec![
        Message::new("system", prompts.system(opts)),
        Message::new("user", prompts.request(&scene(max_agents), &request)),
    ];
    if estimate_tokens(&whole) <= window.prompt() {
        return Ok(Fitted {
            messages: whole,
            left_out: Vec::new(),
        });
    }
    // The example nearest the request: the one named after a behaviour it asks for.
    let behaviours = requests
        .iter()
        .flat_map(|r| request_behaviours(r))
        .collect::<Vec<_>>();
    let best: Vec<(String, String)> = all
        .iter()
        .find(|(name, _)| {
            behaviours
                .iter()
                .any(|b| name == &format!("{}.md", b.name()))
        })
        .or(all.first())
        .into_iter()
        .cloned()
        .collect();
    // What the rules and reasoning mention, and what the request's behaviours use.
    let mut base = used_names(&code_of(&prompts.system_with(opts, &[], "")));
    base.extend(request_names(requests));
    if !opts.frenet {
        // The no-Frenet ablation keeps its functions out, compact or not.
        for e in entries().iter().filter(|e| e.section == "Frenet frame") {
            for n in &e.names {
                base.remove(n);
            }
        }
    }
    let mut agent_steps: Vec<usize> = [max_agents, 12, 8, keep.max(4)]
        .into_iter()
        .map(|n| n.clamp(keep.min(max_agents), max_agents))
        .collect();
    agent_steps.dedup();
    let mut plans: Vec<(&[(String, String)], usize, bool)> = Vec::new();
    for &n in &agent_steps {
        plans.push((all, n, true));
    }
    let fewest = *agent_steps.last().expect("at least one step");
    plans.push((&best, fewest, true));
    // A worked example teaches a small model more than the explanations of functions it shows.
    plans.push((&best, fewest, false));
    plans.push((&[], fewest, true));
    plans.push((&[], fewest, false));
    let mut smallest = u64::MAX;
    for (examples, agents, docs) in plans {
        let mut needed = base.clone();
        for (_, text) in examples {
            needed.extend(used_names(&code_of(text)));
        }
        let (reference, dropped) = compact_reference(&needed, docs);
        let messages = build(examples, &reference, agents);
        let tokens = estimate_tokens(&messages);
        smallest = smallest.min(tokens);
        if tokens > window.prompt() {
            continue;
        }
        let mut left_out = vec![format!(
            "{dropped} entries of the reference that the rules, the examples and the request's \
             behaviours do not use"
        )];
        if agents < max_agents {
            left_out.push(format!(
                "the scene's agents beyond the {agents} nearest the named ones"
            ));
        }
        if examples.len() < all.len() {
            let gone: Vec<&str> = all
                .iter()
                .filter(|(n, _)| !examples.iter().any(|(m, _)| m == n))
                .map(|(n, _)| n.as_str())
                .collect();
            left_out.push(format!("the worked examples {}", gone.join(", ")));
        }
        if !docs {
            left_out.push("the reference's explanations (signatures only)".into());
        }
        return Ok(Fitted { messages, left_out });
    }
    Err(FirstTooLarge { smallest, window })
}

/// The summary of an older exchange, in a line or two, and whether it must stay: a message
/// adding one of `follow_ups` (the requests of `ask --continue`) is summarised as that request,
/// which the model must not lose with the rounds before it.
fn summarise(m: &Message, follow_ups: &[String]) -> (String, bool) {
    if m.role == "user" {
        let added: Vec<&str> = follow_ups
            .iter()
            .map(|r| r.trim())
            .filter(|r| !r.is_empty() && m.content.contains(r))
            .collect();
        if !added.is_empty() {
            return (
                format!("- you were asked besides: {}", added.join("; ")),
                true,
            );
        }
    }
    (summarise_exchange(m), false)
}

fn summarise_exchange(m: &Message) -> String {
    if m.role == "assistant" {
        let code = code_of(&m.content);
        let terms: Vec<&str> = m
            .content
            .split("term(\"")
            .skip(1)
            .filter_map(|t| t.split('"').next())
            .collect();
        if code.trim().is_empty() {
            let first = m
                .content
                .lines()
                .find(|l| !l.trim().is_empty())
                .unwrap_or("");
            return format!("- you replied: {}", first.trim());
        }
        return format!(
            "- you sent a script of {} lines with the terms {}",
            code.lines().count(),
            if terms.is_empty() {
                "(none)".to_string()
            } else {
                terms.join(", ")
            }
        );
    }
    let verdicts: Vec<&str> = m
        .content
        .lines()
        .filter(|l| l.starts_with("## Sample"))
        .map(|l| l.trim_start_matches("## "))
        .collect();
    let first = m
        .content
        .lines()
        .find(|l| !l.trim().is_empty())
        .unwrap_or("");
    if verdicts.is_empty() {
        format!("- drivescript answered: {}", first.trim())
    } else {
        format!("- drivescript sampled it: {}", verdicts.join("; "))
    }
}

/// A refinement message without what a model needs least to repair a script: the realism
/// rows of the term table (the sampler's, not the script's) and the motion tables of every
/// sample after `keep_motion` (all of them with 0). `None` when there is nothing to leave out.
pub fn compact_feedback(text: &str, keep_motion: usize) -> Option<String> {
    let mut out = Vec::new();
    let mut sample = None::<usize>;
    let mut dropped = false;
    for line in text.lines() {
        if let Some(rest) = line.strip_prefix("## Sample ") {
            sample = rest.split(':').next().and_then(|k| k.trim().parse().ok());
        }
        let realism_row = line.starts_with("| realism_");
        let motion = sample.is_some_and(|k| k >= keep_motion)
            && (line.starts_with("Agent ") || line.starts_with("  "));
        if realism_row || motion {
            dropped = true;
            continue;
        }
        out.push(line);
    }
    dropped.then(|| out.join("\n") + "\n")
}

/// `messages` fitted to `budget` tokens: as they are when they fit; else the first two
/// messages (the system prompt and the request), with a summary of the rounds between appended
/// to the request (so that roles still alternate), and the last exchange (the model's last
/// reply and the message after it); else that with the last message's realism rows and all
/// but one sample's motion left out, the oldest summaries left out where even they are too
/// long; else the first two messages as `refit(tokens)` makes them within the tokens left (the
/// first prompt's fitting, one step further; its error is the fewest tokens that prompt takes).
/// A summary line of a message that added one of `follow_ups` (`ask --continue`) is never left
/// out. The error is the fewest tokens the conversation takes, for the message that refuses it.
pub fn fit_conversation(
    messages: &[Message],
    budget: u64,
    follow_ups: &[String],
    refit: &dyn Fn(u64) -> Result<Fitted, u64>,
) -> Result<Fitted, u64> {
    let whole = estimate_tokens(messages);
    if whole <= budget {
        return Ok(Fitted {
            messages: messages.to_vec(),
            left_out: Vec::new(),
        });
    }
    if messages.len() < 4 {
        return Err(whole);
    }
    let (head, rest) = messages.split_at(2);
    let (middle, last) = rest.split_at(rest.len() - 2);
    let lines: Vec<(String, bool)> = middle.iter().map(|m| summarise(m, follow_ups)).collect();
    let droppable = lines.iter().filter(|(_, pinned)| !pinned).count();
    // The summary lines kept when the `skip` oldest that may go are left out.
    let kept = |skip: usize| -> Vec<String> {
        let mut rank = 0;
        lines
            .iter()
            .filter(|(_, pinned)| {
                if *pinned {
                    return true;
                }
                rank += 1;
                rank > skip
            })
            .map(|(l, _)| l.clone())
            .collect()
    };
    let with_summary = |request: &Message, kept: &[String]| {
        let mut request = request.clone();
        if !kept.is_empty() {
            request.content = format!(
                "{}\n\n# Earlier rounds (summarised to fit the model's context window)\n\n{}\n",
                request.content.trim_end(),
                kept.join("\n")
            );
        }
        request
    };
    let mut lasts = vec![(last.to_vec(), None)];
    for (keep, what) in [
        (
            1,
            "the realism rows and all but the first sample's motion of the last feedback",
        ),
        (
            0,
            "the realism rows and the motion tables of the last feedback",
        ),
    ] {
        if let Some(c) = compact_feedback(&last[1].content, keep) {
            let mut compacted = last.to_vec();
            compacted[1].content = c;
            lasts.push((compacted, Some(what)));
        }
    }
    let said = |skip: usize, cut: Option<&str>| {
        let mut left_out = Vec::new();
        if !middle.is_empty() {
            left_out.push(format!(
                "{} earlier messages ({} of them summarised)",
                middle.len(),
                lines.len() - skip
            ));
        }
        if skip > 0 {
            left_out.push(format!("the {skip} oldest messages wholly"));
        }
        left_out.extend(cut.map(str::to_string));
        left_out
    };
    for (last, cut) in &lasts {
        // The oldest summaries go first when even the summary is too long.
        for skip in 0..=droppable {
            let mut out = vec![head[0].clone(), with_summary(&head[1], &kept(skip))];
            out.extend_from_slice(last);
            if estimate_tokens(&out) <= budget {
                return Ok(Fitted {
                    messages: out,
                    left_out: said(skip, *cut),
                });
            }
        }
    }
    // The first prompt itself, fitted into what the rest leaves, with as many summaries as
    // leave it room.
    let (last, cut) = lasts.last().expect("the exchange as it is");
    let mut fewest = u64::MAX;
    for skip in 0..=droppable {
        let lines = kept(skip);
        let tail = estimate_tokens(last)
            + lines
                .iter()
                .map(|l| super::budget::estimate_text(l) + 1)
                .sum::<u64>()
            + 20;
        let first = match refit(budget.saturating_sub(tail)) {
            Ok(f) => f,
            Err(smallest) => {
                fewest = fewest.min(smallest.saturating_add(tail));
                continue;
            }
        };
        let mut out = vec![
            first.messages[0].clone(),
            with_summary(&first.messages[1], &lines),
        ];
        out.extend_from_slice(last);
        let tokens = estimate_tokens(&out);
        if tokens > budget {
            fewest = fewest.min(tokens);
            continue;
        }
        let mut left_out = said(skip, *cut);
        left_out.extend(
            first
                .left_out
                .into_iter()
                .map(|l| format!("(first prompt) {l}")),
        );
        return Ok(Fitted {
            messages: out,
            left_out,
        });
    }
    Err(fewest)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn calls_and_fields_are_the_names_a_script_uses() {
        let n = used_names(
            "let a = agent(5);\nterm(\"x\", relu(a.frenet(p).d.last()));\nm::over_speed(a, 3)",
        );
        for want in ["agent", "term", "relu", "frenet", "d", "last", "over_speed"] {
            assert!(n.contains(want), "{want}: {n:?}");
        }
        assert!(
            !n.contains("let") && !n.contains("a") && !n.contains("x"),
            "{n:?}"
        );
    }

    #[test]
    fn the_compact_reference_keeps_what_is_needed_and_counts_the_rest() {
        let needed: BTreeSet<String> = ["relu", "last", "over_speed"].map(String::from).into();
        let (md, left) = compact_reference(&needed, true);
        assert!(md.contains("`relu(x) -> same kind`"), "{md}");
        assert!(md.contains("`s.first(), s.last() -> Dual`"), "{md}");
        assert!(md.contains("over_speed(a, limit)"), "{md}");
        assert!(!md.contains("lane_ahead"), "{md}");
        assert!(left > 40, "{left}");
        let (bare, _) = compact_reference(&needed, false);
        assert!(bare.len() < md.len() && bare.contains("`relu(x) -> same kind`"));
    }

    #[test]
    fn later_rounds_keep_the_request_and_the_last_exchange_and_summarise_the_rest() {
        let big = "x".repeat(3000);
        let mut m = vec![
            Message::new("system", "rules"),
            Message::new("user", "# Request\n\nvehicle 1 cuts in"),
        ];
        for k in 0..3 {
            m.push(Message::new(
                "assistant",
                format!("plan {k}\n```rhai\nterm(\"ahead_{k}\", 1.0);\n// {big}\n```\n"),
            ));
            m.push(Message::new(
                "user",
                format!("Agents your script names: 1.\n## Sample 0: does not meet it (1 reasons)\n{big}"),
            ));
        }
        let none = |_: u64| Err(u64::MAX);
        let f = fit_conversation(&m, 2500, &[], &none).unwrap();
        assert_eq!(f.messages.len(), 4);
        assert_eq!(f.messages[0], m[0]);
        assert_eq!(&f.messages[2..], &m[6..]);
        let req = &f.messages[1].content;
        assert!(req.starts_with("# Request\n\nvehicle 1 cuts in"), "{req}");
        assert!(
            req.contains("a script of 2 lines with the terms ahead_0")
                && req.contains("Sample 0: does not meet it"),
            "{req}"
        );
        assert_eq!(
            f.left_out,
            vec!["4 earlier messages (4 of them summarised)"]
        );
        assert!(estimate_tokens(&f.messages) <= 2500);
        // Small conversations are sent as they are; one whose last exchange alone is too big
        // cannot be fitted.
        assert_eq!(
            fit_conversation(&m, 1_000_000, &[], &none)
                .unwrap()
                .messages,
            m
        );
        assert!(fit_conversation(&m, 1000, &[], &none).is_err());
        // The last feedback loses the realism rows and the later samples' motion first.
        let fb = "| t | 1 |\n| realism_speed | 2 |\n## Sample 0: ok\nAgent 1: t\n  0 s: a\n## Sample 1: not\n- term x\nAgent 1: t\n  0 s: b\n";
        assert_eq!(
            compact_feedback(fb, 1).unwrap(),
            "| t | 1 |\n## Sample 0: ok\nAgent 1: t\n  0 s: a\n## Sample 1: not\n- term x\n"
        );
        assert_eq!(
            compact_feedback(fb, 0).unwrap(),
            "| t | 1 |\n## Sample 0: ok\n## Sample 1: not\n- term x\n"
        );
        assert_eq!(compact_feedback("## Sample 0: ok\n- fine\n", 0), None);
        // Where even that is too long, the first prompt is fitted into what is left.
        let refit = |tokens: u64| {
            if tokens >= 10 {
                Ok(Fitted {
                    messages: vec![Message::new("system", "r"), Message::new("user", "q")],
                    left_out: vec!["the worked examples".into()],
                })
            } else {
                Err(10)
            }
        };
        let mut long_rules = m.clone();
        long_rules[0].content = "rules ".repeat(200);
        assert!(fit_conversation(&long_rules, 2300, &[], &none).is_err());
        let f = fit_conversation(&long_rules, 2300, &[], &refit).unwrap();
        assert!(f.messages[1].content.starts_with("q\n\n# Earlier rounds"));
        assert!(f
            .left_out
            .iter()
            .any(|l| l == "(first prompt) the worked examples"));
    }

    #[test]
    fn a_follow_up_request_is_never_summarised_away_and_a_misfit_says_its_size() {
        let big = "x".repeat(3000);
        let m = vec![
            Message::new("system", "rules"),
            Message::new("user", "# Request\n\nvehicle 1 cuts in"),
            Message::new("assistant", "```rhai\nterm(\"a\", 1.0);\n```\n"),
            Message::new("user", format!("Sampled: {big}")),
            Message::new("assistant", "ACCEPT"),
            Message::new(
                "user",
                "# Follow-up request\n\nvehicle 2 stops\n\nRevise the current script.",
            ),
            Message::new(
                "assistant",
                format!("```rhai\nterm(\"b\", 1.0);\n// {big}\n```\n"),
            ),
            Message::new("user", format!("## Sample 0: does not meet it\n{big}")),
        ];
        let none = |_: u64| Err(u64::MAX);
        // Room for the request, the last exchange and a line or two of summary: the
        // 1000-token summary of the first feedback goes, the follow-up stays.
        let base = estimate_tokens(&[m[0].clone(), m[1].clone(), m[6].clone(), m[7].clone()]);
        let budget = base + 45;
        let f = fit_conversation(&m, budget, &["vehicle 2 stops".into()], &none).unwrap();
        assert!(estimate_tokens(&f.messages) <= budget);
        assert!(
            f.messages[1]
                .content
                .contains("- you were asked besides: vehicle 2 stops"),
            "{}",
            f.messages[1].content
        );
        assert!(f
            .left_out
            .iter()
            .any(|l| l.contains("oldest messages wholly")));
        // Not known as a follow-up, the message is summarised by its first line.
        let f = fit_conversation(&m, budget, &[], &none).unwrap();
        assert!(!f.messages[1].content.contains("vehicle 2 stops"));
        // Nothing fits: the error is the fewest tokens it takes, the smallest first prompt
        // and the most compact rest.
        let refit = |tokens: u64| {
            if tokens >= 500 {
                Ok(Fitted {
                    messages: vec![],
                    left_out: vec![],
                })
            } else {
                Err(500)
            }
        };
        let fewest = fit_conversation(&m, 1500, &["vehicle 2 stops".into()], &refit).unwrap_err();
        assert!(fewest > 1500 + 500, "{fewest}");
    }
}
