//! Prompt assembly from the plain files in `prompts/` (editable without recompiling): the
//! system prompt with its chain of thought, the worked examples and the stdlib reference
//! generated from the engine's own registry, and the messages of later rounds.
//!
//! A file is a template: `{{name}}` is replaced by the named part. A placeholder a file may not
//! use, or a file that is missing, is an error naming the file.

use std::path::{Path, PathBuf};

use super::LlmError;

/// How the model is asked to reason (the paper's ablations).
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Cot {
    /// The designed chain: events, agents, behaviours, map, lane graph, costs.
    Designed,
    /// "Think step by step".
    ZeroShot,
    /// Request → script directly.
    None,
}

/// Prompt options.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize, serde::Deserialize)]
pub struct PromptOptions {
    /// The reasoning asked for.
    pub cot: Cot,
    /// Whether the reference includes the Frenet-frame functions.
    pub frenet: bool,
}

impl Default for PromptOptions {
    fn default() -> Self {
        Self {
            cot: Cot::Designed,
            frenet: true,
        }
    }
}

/// The templates, read from a directory.
#[derive(Debug, Clone)]
pub struct Prompts {
    dir: PathBuf,
    system: String,
    chain_of_thought: String,
    zero_shot_cot: String,
    no_cot: String,
    request: String,
    refine: String,
    validation: String,
    unusable: String,
    accept_rejected: String,
    followup: String,
    examples: Vec<(String, String)>,
}

/// Each template and the placeholders it may use.
/// Refuses an example the model would learn a wrong script from: one without exactly one
/// ```rhai block (a file that is no example at all, `/etc/passwd` linked in, say), or whose
/// script does not compile (syntax, imports, limits; on no particular scene).
fn check_example(path: &Path, text: &str) -> Result<(), LlmError> {
    let bad = |message: String| LlmError::Prompt {
        path: path.to_path_buf(),
        message,
    };
    match super::reply::parse_reply(text) {
        Ok(super::reply::Reply::Script { source, .. }) => crate::cost::CostScript::check_syntax(
            &source,
            &path.display().to_string(),
            &crate::cost::Limits::default(),
        )
        .map_err(|e| bad(format!("its script does not compile: {e}"))),
        Ok(super::reply::Reply::Accept { .. }) => Err(bad(
            "an example must show a script in one ```rhai block; this one has none".into(),
        )),
        Err(e) => Err(bad(format!("not a worked example: {e}"))),
    }
}

/// The most a prompt template or example may hold: the system prompt is a few KB, and every
/// template goes to the model with each request.
pub const MAX_TEMPLATE_BYTES: u64 = 256 << 10;

/// The most the templates and examples of a prompt folder may hold together: the shipped
/// ones hold about 10 KB. Each file's cap alone let 400 examples make a 100 MB system prompt,
/// sent again with every request and kept in the run's transcript at every round.
pub const MAX_PROMPTS_BYTES: u64 = 1 << 20;

/// Each template: the placeholders it may use, and those it must, without which the model
/// would never hear what it has to act on (an empty `request.md` sent no request, and the
/// model answered a scene nobody described).
const FILES: &[(&str, &[&str], &[&str])] = &[
    (
        "system.md",
        &["reasoning", "examples", "reference"],
        &["reference"],
    ),
    ("chain_of_thought.md", &[], &[]),
    ("zero_shot_cot.md", &[], &[]),
    ("no_cot.md", &[], &[]),
    ("request.md", &["scene", "request"], &["scene", "request"]),
    ("refine.md", &["samples", "feedback"], &["feedback"]),
    ("validation.md", &["horizon", "dt", "error"], &["error"]),
    ("unusable.md", &["error"], &["error"]),
    ("accept_rejected.md", &["reasons"], &["reasons"]),
    (
        "followup.md",
        &["request", "script"],
        &["request", "script"],
    ),
];

impl Prompts {
    /// The repository's `prompts/` (next to the working directory's `data/`, else the
    /// crate's).
    pub fn default_dir() -> PathBuf {
        let here = PathBuf::from("prompts");
        if here.join("system.md").exists() {
            return here;
        }
        PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("prompts")
    }

    /// Reads every template from `dir` (examples from `dir/examples/*.md`, in name order) and
    /// checks their placeholders.
    pub fn load(dir: &Path) -> Result<Self, LlmError> {
        // A folder that is not there (or a file) was "prompt template DIR/system.md: cannot
        // read it: No such file or directory", as if one template of it were missing.
        let folder = |why: &str| {
            Err(LlmError::Setup(format!(
                "the prompt folder {} (--prompts) {why}: it holds system.md, request.md and the \
                 other templates, and examples/ (the shipped one is prompts/)",
                crate::io::name::terminal_safe(&dir.display().to_string())
            )))
        };
        match std::fs::metadata(dir) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return folder("does not exist"),
            Ok(m) if !m.is_dir() => return folder("is a file, not a folder"),
            _ => {}
        }
        let mut total = 0u64;
        let mut read = |name: &str,
                        allowed: &[&str],
                        required: &[&str]|
         -> Result<String, LlmError> {
            let p = dir.join(name);
            let text = crate::io::read_regular_text(&p, MAX_TEMPLATE_BYTES, "a prompt template")
                .map_err(|e| LlmError::Prompt {
                    path: p.clone(),
                    message: format!("cannot read it: {}", e.reason()),
                })?;
            // A control character is nothing a model reads, and `prompt show` prints the
            // templates as they are: an escape sequence in a shared prompt folder reached the
            // terminal (cleared it, retitled the window).
            if let Some((line, c)) = text.lines().enumerate().find_map(|(k, l)| {
                l.chars()
                    .find(|&c| c.is_control() && c != '\t')
                    .map(|c| (k + 1, c))
            }) {
                return Err(LlmError::Prompt {
                    path: p,
                    message: format!(
                        "line {line} holds the control character U+{:04X}: a template is \
                         text for the model; remove it",
                        c as u32
                    ),
                });
            }
            total += text.len() as u64;
            if total > MAX_PROMPTS_BYTES {
                return Err(LlmError::Prompt {
                    path: p,
                    message: format!(
                        "with it the templates and examples hold {} KB, over the {} KB a \
                         prompt folder may hold together (every request sends them all): \
                         keep fewer or shorter examples",
                        total >> 10,
                        MAX_PROMPTS_BYTES >> 10
                    ),
                });
            }
            check_placeholders(&text, allowed, required).map_err(|message| LlmError::Prompt {
                path: p.clone(),
                message,
            })?;
            Ok(text)
        };
        let mut got = Vec::new();
        for (name, allowed, required) in FILES {
            got.push(read(name, allowed, required)?);
        }
        let mut examples = Vec::new();
        let ex = dir.join("examples");
        // Anything but a directory there (a file, a dangling link) is a mistake: skipped, the
        // model was asked with no worked example and nothing said so.
        if ex.symlink_metadata().is_ok() && !ex.is_dir() {
            return Err(LlmError::Prompt {
                path: ex,
                message: "not a directory: `examples/` holds the worked examples, one .md file \
                          each"
                    .into(),
            });
        }
        if ex.is_dir() {
            let mut files: Vec<PathBuf> = std::fs::read_dir(&ex)
                .map_err(|e| LlmError::Prompt {
                    path: ex.clone(),
                    message: format!("cannot list it: {e}"),
                })?
                .filter_map(|e| e.ok().map(|e| e.path()))
                .filter(|p| p.extension().is_some_and(|x| x == "md"))
                .collect();
            files.sort();
            for p in files {
                let name = p
                    .file_name()
                    .unwrap_or_default()
                    .to_string_lossy()
                    .into_owned();
                let text = read(&format!("examples/{name}"), &[], &[])?;
                check_example(&p, &text)?;
                examples.push((name.clone(), text));
            }
        }
        let mut it = got.into_iter();
        let mut next = || it.next().expect("one text per file");
        Ok(Self {
            dir: dir.to_path_buf(),
            system: next(),
            chain_of_thought: next(),
            zero_shot_cot: next(),
            no_cot: next(),
            request: next(),
            refine: next(),
            validation: next(),
            unusable: next(),
            accept_rejected: next(),
            followup: next(),
            examples,
        })
    }

    /// Where they were read from.
    pub fn dir(&self) -> &Path {
        &self.dir
    }

    /// The worked examples, by file name.
    pub fn examples(&self) -> &[(String, String)] {
        &self.examples
    }

    /// The system prompt: rules, the chosen reasoning, the examples and the reference.
    pub fn system(&self, opts: &PromptOptions) -> String {
        let reference = if opts.frenet {
            crate::cost::reference_markdown()
        } else {
            crate::cost::reference_markdown_without(&["Frenet frame"])
        };
        self.system_with(opts, &self.examples, &reference)
    }

    /// The system prompt with these examples and this reference (a context window too small
    /// for all of them gets fewer: [`super::fit`]).
    pub fn system_with(
        &self,
        opts: &PromptOptions,
        examples: &[(String, String)],
        reference: &str,
    ) -> String {
        let reasoning = match opts.cot {
            Cot::Designed => &self.chain_of_thought,
            Cot::ZeroShot => &self.zero_shot_cot,
            Cot::None => &self.no_cot,
        };
        let examples = if examples.is_empty() {
            String::new()
        } else {
            let body: Vec<String> = examples
                .iter()
                .map(|(_, t)| match opts.cot {
                    // Without the chain, the examples are request → script.
                    Cot::Designed => t.trim().to_string(),
                    _ => strip_reasoning(t),
                })
                .collect();
            format!("# Worked examples\n\n{}", body.join("\n\n"))
        };
        fill(
            &self.system,
            &[
                ("reasoning", reasoning.trim()),
                ("examples", &examples),
                ("reference", reference.trim()),
            ],
        )
    }

    /// The first user message: the scene summary and the request.
    pub fn request(&self, scene: &str, request: &str) -> String {
        fill(
            &self.request,
            &[("scene", scene.trim()), ("request", request.trim())],
        )
    }

    /// The refinement message after sampling.
    pub fn refine(&self, samples: usize, feedback: &str) -> String {
        fill(
            &self.refine,
            &[
                ("samples", &samples.to_string()),
                ("feedback", feedback.trim()),
            ],
        )
    }

    /// The message after a failed validation.
    pub fn validation(&self, horizon: usize, dt: f64, error: &str) -> String {
        fill(
            &self.validation,
            &[
                ("horizon", &horizon.to_string()),
                ("dt", &dt.to_string()),
                ("error", error.trim()),
            ],
        )
    }

    /// The message after an unusable reply.
    pub fn unusable(&self, error: &str) -> String {
        fill(&self.unusable, &[("error", error.trim())])
    }

    /// The message after an ACCEPT the numbers contradict.
    pub fn accept_rejected(&self, reasons: &str) -> String {
        fill(&self.accept_rejected, &[("reasons", reasons.trim())])
    }

    /// A follow-up request on an earlier run's script.
    pub fn followup(&self, request: &str, script: &str) -> String {
        fill(
            &self.followup,
            &[("request", request.trim()), ("script", script.trim_end())],
        )
    }
}

/// The example without its numbered reasoning: its title and its code block.
fn strip_reasoning(t: &str) -> String {
    let mut out = Vec::new();
    let mut in_code = false;
    for line in t.lines() {
        if line.trim_start().starts_with("```") {
            in_code = !in_code;
            out.push(line);
        } else if in_code || line.starts_with('#') {
            out.push(line);
        }
    }
    out.join("\n")
}

fn check_placeholders(text: &str, allowed: &[&str], required: &[&str]) -> Result<(), String> {
    let mut used = Vec::new();
    let mut rest = text;
    while let Some(i) = rest.find("{{") {
        let Some(j) = rest[i..].find("}}") else {
            return Err("a `{{` is never closed with `}}`".into());
        };
        let name = rest[i + 2..i + j].trim();
        if !allowed.contains(&name) {
            return Err(format!(
                "unknown placeholder {{{{{name}}}}}; this file may use {}",
                if allowed.is_empty() {
                    "none".to_string()
                } else {
                    allowed
                        .iter()
                        .map(|a| format!("{{{{{a}}}}}"))
                        .collect::<Vec<_>>()
                        .join(", ")
                }
            ));
        }
        used.push(name);
        rest = &rest[i + j + 2..];
    }
    let missing: Vec<String> = required
        .iter()
        .filter(|r| !used.contains(r))
        .map(|r| format!("{{{{{r}}}}}"))
        .collect();
    if !missing.is_empty() {
        let must: Vec<String> = required.iter().map(|r| format!("{{{{{r}}}}}")).collect();
        return Err(format!(
            "{}: this file must use {}, or the model is never told what they stand for",
            if text.trim().is_empty() {
                "empty".to_string()
            } else {
                format!("never uses {}", missing.join(" or "))
            },
            must.join(" and ")
        ));
    }
    Ok(())
}

fn fill(template: &str, parts: &[(&str, &str)]) -> String {
    let mut out = String::with_capacity(template.len());
    let mut rest = template;
    while let Some(i) = rest.find("{{") {
        out.push_str(&rest[..i]);
        let Some(j) = rest[i..].find("}}") else { break };
        let name = rest[i + 2..i + j].trim();
        match parts.iter().find(|(n, _)| *n == name) {
            Some((_, v)) => out.push_str(v),
            None => out.push_str(&rest[i..i + j + 2]),
        }
        rest = &rest[i + j + 2..];
    }
    out.push_str(rest);
    out.trim().to_string() + "\n"
}

#[cfg(test)]
mod tests {
    use super::*;

    fn shipped() -> Prompts {
        Prompts::load(&Path::new(env!("CARGO_MANIFEST_DIR")).join("prompts")).unwrap()
    }

    #[test]
    fn the_system_prompt_carries_the_generated_reference_and_the_chosen_reasoning() {
        let p = shipped();
        let s = p.system(&PromptOptions::default());
        assert!(s.contains(crate::cost::reference_markdown().trim()));
        assert!(s.contains("explore the"), "the designed chain is missing");
        assert!(
            s.contains("```rhai\nlet a = agent(2);"),
            "the examples are missing"
        );
        assert!(!s.contains("{{"), "a placeholder was left: {s}");
        let z = p.system(&PromptOptions {
            cot: Cot::ZeroShot,
            frenet: false,
        });
        assert!(z.contains("Think step by step") && !z.contains("explore the"));
        assert!(!z.contains("## Frenet frame") && s.contains("## Frenet frame"));
        // Without the chain the examples keep their scripts, not their reasoning.
        assert!(z.contains("let a = agent(2);") && !z.contains("1. Events: one, a cut-in."));
    }

    #[test]
    fn every_example_script_compiles_and_the_cut_in_validates_on_the_test_highway() {
        let p = shipped();
        assert!(p.examples().len() >= 3);
        let scene = std::rc::Rc::new(
            crate::io::load_scene(
                &Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml"),
                0,
                &crate::io::LoadOptions::default(),
            )
            .unwrap(),
        );
        for (name, text) in p.examples() {
            let Ok(super::super::reply::Reply::Script { source, .. }) =
                super::super::reply::parse_reply(text)
            else {
                panic!("{name}: no script block");
            };
            let c = crate::cost::CostScript::compile(
                &source,
                name,
                scene.clone(),
                &crate::cost::Params::default(),
                &crate::cost::Limits::default(),
            )
            .unwrap_or_else(|e| panic!("{name}: {e}"));
            if name == "cut_in.md" {
                c.validate().unwrap_or_else(|e| panic!("{name}: {e}"));
            }
        }
    }

    #[test]
    fn examples_that_do_not_compile_or_are_no_examples_are_refused() {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("prompts");
        for (text, want) in [
            (
                "## Example\n\n```rhai\nterm(\"x\", agent(1).x.last() - );\n```\n",
                "its script does not compile",
            ),
            (
                "root:x:0:0:root:/root:/bin/bash\n",
                "not a worked example: the reply has no ```rhai code block",
            ),
        ] {
            let dir = tempfile::tempdir().unwrap();
            for (name, _, _) in FILES {
                std::fs::copy(src.join(name), dir.path().join(name)).unwrap();
            }
            std::fs::create_dir(dir.path().join("examples")).unwrap();
            std::fs::write(dir.path().join("examples/bad.md"), text).unwrap();
            let e = Prompts::load(dir.path()).unwrap_err().to_string();
            assert!(e.contains("examples/bad.md") && e.contains(want), "{e}");
        }
    }

    #[test]
    fn a_bad_template_names_its_file_and_placeholder() {
        let dir = tempfile::tempdir().unwrap();
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("prompts");
        for (name, _, _) in FILES {
            std::fs::copy(src.join(name), dir.path().join(name)).unwrap();
        }
        std::fs::write(dir.path().join("refine.md"), "{{feedback}} {{secret}}").unwrap();
        let e = Prompts::load(dir.path()).unwrap_err().to_string();
        assert!(e.contains("refine.md") && e.contains("{{secret}}"), "{e}");
        // A template that never says what it carries (an empty request.md sent the model no
        // request and no scene, exit 0).
        std::fs::copy(src.join("refine.md"), dir.path().join("refine.md")).unwrap();
        for (name, text, want) in [
            (
                "request.md",
                "",
                "request.md: empty: this file must use {{scene}} and {{request}}",
            ),
            (
                "request.md",
                "Scene: {{scene}}",
                "request.md: never uses {{request}}: this file must use {{scene}} and {{request}}",
            ),
            (
                "system.md",
                "  \n",
                "system.md: empty: this file must use {{reference}}",
            ),
            (
                "refine.md",
                "{{samples}}",
                "refine.md: never uses {{feedback}}",
            ),
        ] {
            let before = std::fs::read(dir.path().join(name)).unwrap();
            std::fs::write(dir.path().join(name), text).unwrap();
            let e = Prompts::load(dir.path()).unwrap_err().to_string();
            assert!(e.contains(want), "{e}");
            std::fs::write(dir.path().join(name), before).unwrap();
        }
        // Printed as they are by `prompt show`: an escape sequence reached the terminal.
        let before = std::fs::read(dir.path().join("request.md")).unwrap();
        std::fs::write(
            dir.path().join("request.md"),
            "{{scene}}\r\n\u{1b}]0;pwned\u{7}{{request}}\n",
        )
        .unwrap();
        let e = Prompts::load(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("request.md: line 2 holds the control character U+001B"),
            "{e}"
        );
        std::fs::write(dir.path().join("request.md"), before).unwrap();
        Prompts::load(dir.path()).unwrap();
        std::fs::remove_file(dir.path().join("request.md")).unwrap();
        let e = Prompts::load(dir.path()).unwrap_err().to_string();
        assert!(e.contains("request.md") && e.contains("cannot read"), "{e}");
    }

    /// Each file within its cap, 400 examples made a 100 MB system prompt sent with every
    /// request; `examples` as a file left the model without examples, exit 0 (issue 32).
    #[test]
    fn a_prompt_folder_past_its_total_or_with_examples_not_a_directory_is_refused() {
        let src = Path::new(env!("CARGO_MANIFEST_DIR")).join("prompts");
        let dir = tempfile::tempdir().unwrap();
        for (name, _, _) in FILES {
            std::fs::copy(src.join(name), dir.path().join(name)).unwrap();
        }
        std::fs::write(dir.path().join("examples"), "not a folder").unwrap();
        let e = Prompts::load(dir.path()).unwrap_err().to_string();
        assert!(e.contains("examples: not a directory"), "{e}");
        std::fs::remove_file(dir.path().join("examples")).unwrap();
        std::fs::create_dir(dir.path().join("examples")).unwrap();
        let example = std::fs::read_to_string(src.join("examples/cut_in.md")).unwrap();
        let big = format!("{example}\n{}", "filler ".repeat(30_000));
        for i in 0..6 {
            std::fs::write(dir.path().join(format!("examples/e{i}.md")), &big).unwrap();
        }
        let e = Prompts::load(dir.path()).unwrap_err().to_string();
        assert!(
            e.contains("examples/e4.md") && e.contains("over the 1024 KB a prompt folder"),
            "{e}"
        );
    }
}
