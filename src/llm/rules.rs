//! The rules planner: a small deterministic planner, not a language model. It recognises the
//! paper's vocabulary of behaviours with vehicle ids (and conjunctions of them), composes the
//! scripts of `scripts/` with their parameters bound into one script, and repairs by
//! strengthening the terms of the events that failed. It makes `ask` work without a model, is
//! the baseline a model must beat, and names the independent checkers of a request whatever
//! backend writes its script.

use std::fmt::Write as _;

use crate::cost::{ParamValue, Params};
use crate::eval::behaviors::Behavior;

/// One event of a request: a known behaviour with its agents and arguments.
#[derive(Debug, Clone, PartialEq)]
pub struct Event {
    /// The behaviour.
    pub behaviour: Behavior,
    /// Its parameters, as the checker and the script both read them (agent roles, limits).
    pub params: Params,
    /// The words it came from.
    pub clause: String,
}

/// Why the rules planner cannot plan a request.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum RulesError {
    /// Nothing in the request is a behaviour it knows.
    #[error(
        "the rules planner (a fixed vocabulary, not a language model) does not understand \"{}\". \
         It knows: {vocabulary}, each with vehicle ids (\"vehicle 3 cuts in front of vehicle 5, \
         vehicle 7 drives off the road\"). For free text, run `drivescript ask` with an LLM: \
         set DRIVESCRIPT_LLM_URL and DRIVESCRIPT_LLM_MODEL (or pass --llm-url and --model), or \
         use --llm manual to paste prompts into any chat",
        crate::io::name::shown_counted(.clause)
    )]
    NotUnderstood {
        /// The clause.
        clause: String,
        /// What it knows.
        vocabulary: String,
    },
    /// A behaviour without the vehicles or numbers it needs.
    #[error(
        "\"{}\": the rules planner reads this as {behaviour}, which needs {what}; for \
         requests outside its fixed vocabulary, run `drivescript ask` with an LLM \
         (DRIVESCRIPT_LLM_URL and DRIVESCRIPT_LLM_MODEL, or --llm manual)",
        crate::io::name::shown_counted(.clause)
    )]
    Missing {
        /// The clause.
        clause: String,
        /// The behaviour.
        behaviour: &'static str,
        /// What is missing, in words.
        what: String,
    },
    /// A request longer, or of more events, than one composed script holds: the script
    /// quotes every clause and adds a block per event, and a 100,000-character request
    /// failed validation as a script too large, blaming the script.
    #[error(
        "the request \"{}\" is too long for the rules planner: {what} (it reads at most \
         {MAX_REQUEST_CHARS} characters and {MAX_REQUEST_EVENTS} events); say it in fewer words, \
         or run `drivescript ask` with an LLM",
        crate::io::name::shown_counted(.request)
    )]
    TooLong {
        /// The request.
        request: String,
        /// What is over the limit, in words ("100034 characters").
        what: String,
    },
}

/// The longest request the rules planner reads, in characters: a request of its vocabulary is
/// a sentence or a few.
pub const MAX_REQUEST_CHARS: usize = 2_000;
/// The most events one request may name: each adds a block of about a kilobyte to the
/// composed script, which must stay inside the engine's size limit after repairs.
pub const MAX_REQUEST_EVENTS: usize = 20;

/// Phrases per behaviour, in the order they are tried (negated collisions before accidents,
/// rightmost before right).
const PHRASES: &[(Behavior, &[&str])] = &[
    (
        Behavior::NoCollisions,
        &[
            "no collision",
            "no collisions",
            "without collision",
            "without collisions",
            "without colliding",
            "avoid collision",
            "avoid collisions",
            "avoids collision",
            "avoids collisions",
            "collision-free",
            "collision free",
            "never collide",
            "nobody collides",
            "no one collides",
        ],
    ),
    (
        Behavior::Accident,
        &[
            "crashes into",
            "crash into",
            "collides with",
            "collide with",
            "rams",
            "hits",
            "accident",
            "rear-ends",
            "rear ends",
        ],
    ),
    (
        Behavior::CutIn,
        &[
            "cuts in",
            "cut in",
            "cut-in",
            "cuts-in",
            "cutting in",
            "cuts off",
        ],
    ),
    (
        Behavior::RightmostLane,
        &["rightmost", "right-most", "outermost lane", "slow lane"],
    ),
    (
        Behavior::OffRoad,
        &[
            "off the road",
            "off road",
            "off-road",
            "out of the road",
            "out of road",
            "leaves the road",
            "leave the road",
            "road departure",
        ],
    ),
    (
        Behavior::Yield,
        &["yields", "yield", "gives way", "give way", "lets"],
    ),
    (Behavior::Follow, &["follows", "follow", "following"]),
    (
        Behavior::Reverse,
        &["reverse", "reverses", "backs up", "backwards", "back up"],
    ),
    (
        Behavior::Weave,
        &[
            "weave",
            "weaves",
            "weaving",
            "zigzag",
            "zig-zag",
            "swerves left and right",
        ],
    ),
    (
        Behavior::SpeedLimit,
        &[
            "speed limit",
            "below",
            "under",
            "at most",
            "no faster than",
            "slower than",
            "limit",
        ],
    ),
    (
        Behavior::TargetPoint,
        &[
            "target point",
            "reaches",
            "reach",
            "goes to",
            "drives to",
            "arrives at",
        ],
    ),
    (
        Behavior::LaneChangeLeft,
        &[
            "left lane change",
            "lane change left",
            "lane change to the left",
            "changes lane to the left",
            "changes lanes to the left",
            "change lane to the left",
            "change lanes to the left",
            "changes to the left lane",
            "moves to the left lane",
            "moves into the left lane",
            "merges left",
        ],
    ),
    (
        Behavior::LaneChangeRight,
        &[
            "right lane change",
            "lane change right",
            "lane change to the right",
            "changes lane to the right",
            "changes lanes to the right",
            "change lane to the right",
            "change lanes to the right",
            "changes to the right lane",
            "moves to the right lane",
            "moves into the right lane",
            "merges right",
        ],
    ),
    (
        Behavior::Stop,
        &[
            "stops",
            "stop",
            "halts",
            "comes to a standstill",
            "brakes to a standstill",
        ],
    ),
    (
        Behavior::TurnLeft,
        &[
            "turns left",
            "turn left",
            "turning left",
            "left turn",
            "takes a left",
            "goes left at",
        ],
    ),
    (
        Behavior::TurnRight,
        &[
            "turns right",
            "turn right",
            "turning right",
            "right turn",
            "takes a right",
            "goes right at",
        ],
    ),
];

fn vocabulary() -> String {
    PHRASES
        .iter()
        .map(|(b, p)| format!("{} (\"{}\")", b.name(), p[0]))
        .collect::<Vec<_>>()
        .join(", ")
}

/// Words that introduce an agent id.
const AGENT_WORDS: &[&str] = &["vehicle", "vehicles", "car", "cars", "agent", "truck", "id"];

/// Splits a request (with commas inside parentheses protected) into events: every clause must
/// be understood.
fn understand(request: &str) -> Result<Vec<Event>, RulesError> {
    let mut events = Vec::new();
    for e in understand_clauses(request) {
        events.push(e?);
    }
    if events.is_empty() {
        return Err(RulesError::NotUnderstood {
            clause: request.trim().to_string(),
            vocabulary: vocabulary(),
        });
    }
    Ok(events)
}

/// Each clause of a request as an event, or why it is not one.
fn understand_clauses(request: &str) -> Vec<Result<Event, RulesError>> {
    let text = request.to_lowercase().replace(['\n', '\t'], " ");
    let mut clauses: Vec<String> = Vec::new();
    for part in split_clauses(&text) {
        let part = part.trim().trim_end_matches('.').trim().to_string();
        if part.is_empty() {
            continue;
        }
        // A fragment with neither a behaviour nor a vehicle continues the clause before it
        // ("weave left and right within the lane").
        if behaviour_of(&part).is_none() && ids(&part).is_empty() {
            if let Some(last) = clauses.last_mut() {
                last.push_str(" and ");
                last.push_str(&part);
                continue;
            }
        }
        clauses.push(part);
    }
    let mut subject: Option<i64> = None;
    clauses
        .into_iter()
        .map(|clause| clause_event(clause, &mut subject))
        .collect()
}

/// The event of one clause; `subject` is the vehicle of the clauses before, for a clause that
/// names none ("vehicle 3 slows down and then stops").
fn clause_event(clause: String, subject: &mut Option<i64>) -> Result<Event, RulesError> {
    {
        let Some(b) = behaviour_of(&clause) else {
            return Err(RulesError::NotUnderstood {
                clause,
                vocabulary: vocabulary(),
            });
        };
        let mut found = ids(&clause);
        // "vehicle 3 slows down and then stops": the subject carries over.
        if found.is_empty() {
            found.extend(*subject);
        }
        *subject = found.first().copied().or(*subject);
        let missing = |what: &str| RulesError::Missing {
            clause: clause.clone(),
            behaviour: b.name(),
            what: what.into(),
        };
        let mut p = Params::default();
        let id = |v: i64| ParamValue::Int(v);
        match b.roles() {
            [] => {}
            [one] => {
                let v = *found.first().ok_or_else(|| missing("a vehicle id"))?;
                p.set(one, id(v));
            }
            [first, second] => {
                if found.len() < 2 {
                    return Err(missing(&format!(
                        "two vehicle ids ({first} and {second}), in that order"
                    )));
                }
                p.set(first, id(found[0]));
                p.set(second, id(found[1]));
            }
            _ => unreachable!("behaviours name at most two agents"),
        }
        match b {
            Behavior::SpeedLimit => {
                let v = speed(&clause).ok_or_else(|| {
                    missing("a speed with its unit (\"below 15 m/s\", \"at most 50 km/h\")")
                })?;
                p.set("limit", ParamValue::Float(round3(v)));
            }
            Behavior::TargetPoint => {
                let (x, y) = point(&clause.replace('\u{1f}', ","))
                    .ok_or_else(|| missing("a point in world coordinates, as (x, y) in metres"))?;
                p.set("x", ParamValue::Float(x));
                p.set("y", ParamValue::Float(y));
            }
            Behavior::Follow => {
                if let Some(g) = number_before(&clause, &["m", "metres", "meters"]) {
                    p.set("gap", ParamValue::Float(g));
                }
            }
            Behavior::Stop => {
                if let Some(s) = number_before(&clause, &["s", "seconds", "second"]) {
                    p.set("within", ParamValue::Float(s));
                }
            }
            _ => {}
        }
        Ok(Event {
            behaviour: b,
            params: p,
            clause,
        })
    }
}

fn split_clauses(text: &str) -> Vec<String> {
    let mut parts = vec![text.to_string()];
    for sep in [";", ",", " while ", " and then ", " then ", " and "] {
        parts = parts
            .iter()
            .flat_map(|p| p.split(sep).map(str::to_string).collect::<Vec<_>>())
            .collect();
    }
    parts
}

fn behaviour_of(clause: &str) -> Option<Behavior> {
    let padded = format!(" {} ", words(clause).join(" "));
    PHRASES.iter().find_map(|(b, phrases)| {
        phrases
            .iter()
            .any(|p| padded.contains(&format!(" {} ", words(p).join(" "))))
            .then_some(*b)
    })
}

/// Lower-case words with punctuation other than `-`, `.` inside numbers and `/` removed.
fn words(s: &str) -> Vec<String> {
    s.split(|c: char| c.is_whitespace() || matches!(c, ',' | ';' | '(' | ')' | '!' | '?' | '"'))
        .map(|w| w.trim_matches(|c: char| c == '.' || c == ':').to_string())
        .filter(|w| !w.is_empty())
        .collect()
}

/// Agent ids in order: numbers after an agent word ("vehicle 3", "cars 3 and 5" gives 3
/// only; "vehicle #3" and "v3" work too).
fn ids(clause: &str) -> Vec<i64> {
    let w = words(clause);
    let mut out = Vec::new();
    for (i, word) in w.iter().enumerate() {
        let mut candidate = None;
        if AGENT_WORDS.contains(&word.as_str()) {
            if let Some(next) = w.get(i + 1) {
                candidate = next.trim_start_matches('#').parse::<i64>().ok();
            }
        } else if let Some(rest) = word.strip_prefix('#').or_else(|| word.strip_prefix('v')) {
            candidate = rest.parse::<i64>().ok().filter(|_| !rest.is_empty());
        }
        if let Some(id) = candidate {
            if !out.contains(&id) {
                out.push(id);
            }
        }
    }
    out
}

fn round3(v: f64) -> f64 {
    (v * 1000.0).round() / 1000.0
}

/// Each number of a clause with its unit (written on or after it: "15m", "15 m").
fn numbers_with_units(clause: &str) -> Vec<(f64, String)> {
    let w = words(clause);
    let mut out = Vec::new();
    for (i, word) in w.iter().enumerate() {
        let (num, unit) = split_number(word);
        let Some(v) = num else { continue };
        let unit = if unit.is_empty() {
            w.get(i + 1).map(String::as_str).unwrap_or("")
        } else {
            unit
        };
        out.push((v, unit.to_string()));
    }
    out
}

/// A speed in m/s from "15 m/s", "50 km/h", "30 mph", "50kph".
fn speed(clause: &str) -> Option<f64> {
    numbers_with_units(clause)
        .into_iter()
        .find_map(|(v, unit)| {
            let factor = match unit.as_str() {
                "m/s" | "mps" => 1.0,
                "km/h" | "kmh" | "kph" | "kmph" => 1.0 / 3.6,
                "mph" => 0.44704,
                _ => return None,
            };
            Some(v * factor)
        })
}

fn split_number(word: &str) -> (Option<f64>, &str) {
    let end = word
        .char_indices()
        .find(|&(i, c)| !(c.is_ascii_digit() || c == '.' || (c == '-' && i == 0)))
        .map_or(word.len(), |(i, _)| i);
    (word[..end].parse().ok(), &word[end..])
}

/// The number before one of `units` ("at 15 m", "within 3 s", "15m").
fn number_before(clause: &str, units: &[&str]) -> Option<f64> {
    numbers_with_units(clause)
        .into_iter()
        .find_map(|(v, unit)| units.contains(&unit.as_str()).then_some(v))
}

/// "(x, y)" in the original clause.
fn point(clause: &str) -> Option<(f64, f64)> {
    let open = clause.find('(')?;
    let close = open + clause[open..].find(')')?;
    let inner = &clause[open + 1..close];
    let mut it = inner.split(',').map(|s| s.trim().parse::<f64>());
    let (x, y) = (it.next()?.ok()?, it.next()?.ok()?);
    (it.next().is_none() && x.is_finite() && y.is_finite()).then_some((x, y))
}

/// The split with commas: "(x, y)" must reach [`point`] whole, so target points are found
/// before splitting.
fn protect_points(request: &str) -> String {
    let mut out = String::new();
    let mut depth = 0;
    for c in request.chars() {
        match c {
            '(' => depth += 1,
            ')' => depth -= 1,
            _ => {}
        }
        out.push(if c == ',' && depth > 0 { '\u{1f}' } else { c });
    }
    out
}

/// How strongly each event's script pulls: its terms' weights are multiplied by `weight`, and
/// its margins are the script's defaults overridden by `margins`.
#[derive(Debug, Clone, PartialEq)]
pub struct Tuning {
    /// Factor on every term weight of the event.
    pub weight: f64,
    /// Script parameters that are margins (never the checker's own parameters).
    pub margins: Params,
}

impl Default for Tuning {
    fn default() -> Self {
        Self {
            weight: 1.0,
            margins: Params::default(),
        }
    }
}

/// The script source of a behaviour, as shipped in `scripts/`.
pub fn script_source(b: Behavior) -> &'static str {
    match b {
        Behavior::SpeedLimit => include_str!("../../scripts/speed_limit.rhai"),
        Behavior::TargetPoint => include_str!("../../scripts/target_point.rhai"),
        Behavior::NoCollisions => include_str!("../../scripts/no_collisions.rhai"),
        Behavior::LaneChangeLeft => include_str!("../../scripts/lane_change_left.rhai"),
        Behavior::LaneChangeRight => include_str!("../../scripts/lane_change_right.rhai"),
        Behavior::RightmostLane => include_str!("../../scripts/rightmost_lane.rhai"),
        Behavior::CutIn => include_str!("../../scripts/cut_in.rhai"),
        Behavior::Yield => include_str!("../../scripts/yield.rhai"),
        Behavior::Follow => include_str!("../../scripts/follow.rhai"),
        Behavior::Reverse => include_str!("../../scripts/reverse.rhai"),
        Behavior::OffRoad => include_str!("../../scripts/off_road.rhai"),
        Behavior::Weave => include_str!("../../scripts/weave.rhai"),
        Behavior::Stop => include_str!("../../scripts/stop.rhai"),
        Behavior::Accident => include_str!("../../scripts/accident.rhai"),
        Behavior::TurnLeft => include_str!("../../scripts/turn_left.rhai"),
        Behavior::TurnRight => include_str!("../../scripts/turn_right.rhai"),
    }
}

/// The margin a repair moves, per behaviour: (script parameter, its default, step, bound).
/// A failing event's margin moves by `step` towards `bound` (asking for more than the checker
/// needs, so that a near miss becomes a pass).
fn margin(b: Behavior) -> Option<(&'static str, f64, f64, f64)> {
    Some(match b {
        Behavior::CutIn => ("tol", 0.5, -0.15, 0.2),
        Behavior::RightmostLane | Behavior::LaneChangeLeft | Behavior::LaneChangeRight => {
            ("tol", 0.5, -0.15, 0.2)
        }
        Behavior::OffRoad => ("distance", 1.0, 1.0, 4.0),
        Behavior::Yield => ("margin", 2.0, 2.0, 8.0),
        Behavior::Follow => ("tol", 0.5, -0.15, 0.2),
        Behavior::Reverse => ("distance", 1.5, 0.5, 3.0),
        Behavior::Weave => ("amplitude", 0.8, 0.2, 1.2),
        Behavior::Stop => ("max_decel", 6.0, 1.0, 8.0),
        Behavior::Accident => ("depth", 0.3, 0.3, 1.5),
        Behavior::TurnLeft | Behavior::TurnRight => ("past", 1.0, 1.0, 4.0),
        Behavior::TargetPoint => ("tol", 1.0, -0.3, 0.3),
        Behavior::NoCollisions => ("margin", 0.5, 0.5, 2.0),
        Behavior::SpeedLimit => return None,
    })
}

/// What a repair does to one event: stronger and stricter when it was not achieved, gentler
/// when it was achieved only with implausible motion. Returns the new tuning and a sentence.
pub fn retune(e: &Event, t: &Tuning, achieved: bool) -> (Tuning, String) {
    let mut next = t.clone();
    let b = e.behaviour;
    let mut said = Vec::new();
    if achieved {
        // The geometry happened but a named car could not drive it: pull less hard.
        next.weight = round3(t.weight * 0.5);
        said.push(format!("weights ×0.5 (now {})", next.weight));
    } else {
        next.weight = round3((t.weight * 2.0).min(16.0));
        said.push(format!("weights ×2 (now {})", next.weight));
        if let Some((name, default, step, bound)) = margin(b) {
            let now = t.margins.number(name).unwrap_or(default);
            let moved = if step > 0.0 {
                (now + step).min(bound)
            } else {
                (now + step).max(bound)
            };
            if moved != now {
                next.margins.set(name, ParamValue::Float(round3(moved)));
                said.push(format!("{name} {now} → {}", round3(moved)));
            }
        }
    }
    (next, format!("{}: {}", b.name(), said.join(", ")))
}

/// One script for all events: each event's script from `scripts/` in its own block, with its
/// parameters bound as literals (so that the script runs as it stands with `simulate
/// --script`), its term weights multiplied by its tuning, and term names made unique.
pub fn compose(events: &[Event], tunings: &[Tuning]) -> String {
    compose_with_terms(events, tunings).0
}

/// [`compose`], also returning each event's term names as the composed script declares them.
pub fn compose_with_terms(events: &[Event], tunings: &[Tuning]) -> (String, Vec<Vec<String>>) {
    let mut per_event = Vec::new();
    let mut out = String::from(
        "// Written by drivescript's rules planner (not a language model) from scripts/.\n",
    );
    let mut names: Vec<String> = Vec::new();
    for (k, e) in events.iter().enumerate() {
        let t = tunings.get(k).cloned().unwrap_or_default();
        let bound = e.params.overridden_by(&t.margins);
        let body = bind_params(script_source(e.behaviour), &bound);
        let before = names.len();
        let body = reweight_terms(&body, t.weight, &mut names);
        per_event.push(names[before..].to_vec());
        let _ = writeln!(
            out,
            "\n// Event {}: {} — {} ({}).",
            k + 1,
            e.clause,
            e.behaviour.name(),
            if bound.is_empty() {
                "no parameters".to_string()
            } else {
                bound.to_string()
            }
        );
        out.push_str("{\n");
        for line in body.lines() {
            if line.trim().is_empty() {
                out.push('\n');
            } else {
                let _ = writeln!(out, "    {line}");
            }
        }
        out.push_str("}\n");
    }
    (out, per_event)
}

fn literal(v: &ParamValue) -> String {
    match v {
        ParamValue::Int(i) if *i < 0 => format!("({i})"),
        ParamValue::Int(i) => i.to_string(),
        ParamValue::Float(f) if *f < 0.0 => format!("({f:?})"),
        ParamValue::Float(f) => format!("{f:?}"),
        ParamValue::Bool(b) => b.to_string(),
        ParamValue::Str(s) => format!("{s:?}"),
    }
}

/// Replaces `param("name")` and `param("name", default)` with the bound value (or the
/// default when unbound).
fn bind_params(src: &str, params: &Params) -> String {
    let mut out = String::new();
    let mut rest = src;
    while let Some(i) = rest.find("param(\"") {
        out.push_str(&rest[..i]);
        let after = &rest[i + 7..];
        let Some(q) = after.find('"') else {
            out.push_str(&rest[i..]);
            return out;
        };
        let name = &after[..q];
        let Some(close) = matching_paren(&rest[i + 5..]) else {
            out.push_str(&rest[i..]);
            return out;
        };
        let call = &rest[i..i + 5 + close + 1];
        let default = call[7 + q + 1..call.len() - 1]
            .trim()
            .trim_start_matches(',')
            .trim();
        match params.get(name) {
            // A float default keeps the value a float (`gap=8` binds 8.0): the stdlib's
            // arithmetic on series takes floats.
            Some(ParamValue::Int(i)) if default.contains('.') => {
                out.push_str(&literal(&ParamValue::Float(*i as f64)))
            }
            Some(v) => out.push_str(&literal(v)),
            None if !default.is_empty() => out.push_str(default),
            None => out.push_str(call),
        }
        rest = &rest[i + 5 + close + 1..];
    }
    out.push_str(rest);
    out
}

/// Index of the `)` that closes the `(` at `s[0]`, skipping strings.
fn matching_paren(s: &str) -> Option<usize> {
    let mut depth = 0i32;
    let mut in_str: Option<char> = None;
    let mut prev = ' ';
    for (i, c) in s.char_indices() {
        match in_str {
            Some(q) => {
                if c == q && prev != '\\' {
                    in_str = None;
                }
            }
            None => match c {
                '"' | '`' => in_str = Some(c),
                '(' => depth += 1,
                ')' => {
                    depth -= 1;
                    if depth == 0 {
                        return Some(i);
                    }
                }
                _ => {}
            },
        }
        prev = c;
    }
    None
}

/// Splits the arguments of a call's inside at top-level commas.
fn split_args(inner: &str) -> Vec<&str> {
    let mut out = Vec::new();
    let (mut depth, mut start) = (0i32, 0);
    let mut in_str: Option<char> = None;
    for (i, c) in inner.char_indices() {
        match in_str {
            Some(q) if c == q => in_str = None,
            Some(_) => {}
            None => match c {
                '"' | '`' => in_str = Some(c),
                '(' | '[' | '{' => depth += 1,
                ')' | ']' | '}' => depth -= 1,
                ',' if depth == 0 => {
                    out.push(&inner[start..i]);
                    start = i + 1;
                }
                _ => {}
            },
        }
    }
    out.push(&inner[start..]);
    out
}

/// Multiplies every `term(...)` weight by `factor` and renames terms already in `names`.
fn reweight_terms(src: &str, factor: f64, names: &mut Vec<String>) -> String {
    let mut out = String::new();
    let mut rest = src;
    loop {
        // A `term(` that is a call, not the end of another identifier.
        let found = rest.match_indices("term(").find(|(i, _)| {
            rest[..*i]
                .chars()
                .next_back()
                .is_none_or(|c| !(c.is_alphanumeric() || c == '_' || c == '.'))
        });
        let Some((i, _)) = found else { break };
        let Some(close) = matching_paren(&rest[i + 4..]) else {
            break;
        };
        let inner = &rest[i + 5..i + 4 + close];
        let args = split_args(inner);
        out.push_str(&rest[..i]);
        if !(2..=4).contains(&args.len()) {
            out.push_str(&rest[i..i + 4 + close + 1]);
            rest = &rest[i + 4 + close + 1..];
            continue;
        }
        let mut name = args[0].trim().to_string();
        if let Some(plain) = name.strip_prefix('"').and_then(|n| n.strip_suffix('"')) {
            let mut unique = plain.to_string();
            let mut n = 2;
            while names.contains(&unique) {
                unique = format!("{plain}_{n}");
                n += 1;
            }
            names.push(unique.clone());
            name = format!("{unique:?}");
        }
        let value = args[1].trim();
        let tolerance = args.get(3).map(|t| t.trim());
        let weight = match (args.get(2).map(|w| w.trim()), factor == 1.0) {
            (None, true) if tolerance.is_none() => None,
            (None, _) => Some(format!("{factor:?}")),
            (Some(w), true) => Some(w.to_string()),
            (Some(w), false) => Some(format!("{factor:?} * {w}")),
        };
        match (weight, tolerance) {
            (Some(w), Some(t)) => out.push_str(&format!("term({name}, {value}, {w}, {t})")),
            (Some(w), None) => out.push_str(&format!("term({name}, {value}, {w})")),
            (None, _) => out.push_str(&format!("term({name}, {value})")),
        }
        rest = &rest[i + 4 + close + 1..];
    }
    out.push_str(rest);
    out
}

/// The plan in words: the chain of thought's result for a recognised request.
pub fn plan_text(events: &[Event]) -> String {
    let mut s = format!(
        "Plan (rules planner): {} event{}.\n",
        events.len(),
        if events.len() == 1 { "" } else { "s" }
    );
    for (k, e) in events.iter().enumerate() {
        let _ = writeln!(
            s,
            "{}. \"{}\" → {} ({}); checker: {}",
            k + 1,
            e.clause,
            e.behaviour.name(),
            if e.params.is_empty() {
                "all vehicles".to_string()
            } else {
                e.params.to_string()
            },
            e.behaviour.definition()
        );
    }
    s
}

/// The events of the clauses of `request` that the planner understands, and the clauses it
/// does not (each with why): a composed request keeps the checkers of the events it names
/// even where another part is outside the vocabulary ("vehicle 114 drives straight").
pub fn understand_partly(request: &str) -> (Vec<Event>, Vec<RulesError>) {
    let protected = protect_points(request);
    let (mut events, mut left) = (Vec::new(), Vec::new());
    for e in understand_clauses(&protected) {
        match e {
            Ok(mut e) => {
                e.clause = e.clause.replace('\u{1f}', ",");
                events.push(e);
            }
            Err(RulesError::NotUnderstood { clause, vocabulary }) => {
                left.push(RulesError::NotUnderstood {
                    clause: clause.replace('\u{1f}', ","),
                    vocabulary,
                })
            }
            Err(RulesError::Missing {
                clause,
                behaviour,
                what,
            }) => left.push(RulesError::Missing {
                clause: clause.replace('\u{1f}', ","),
                behaviour,
                what,
            }),
            // Only `plan_request` says a request is too long.
            Err(e @ RulesError::TooLong { .. }) => left.push(e),
        }
    }
    (events, left)
}

/// [`understand_request`] for a request the rules planner is to write the script of: refused
/// where it is longer, or names more events, than one composed script holds.
pub fn plan_request(request: &str) -> Result<Vec<Event>, RulesError> {
    let chars = request.trim().chars().count();
    if chars > MAX_REQUEST_CHARS {
        return Err(RulesError::TooLong {
            request: request.trim().to_string(),
            what: format!("{chars} characters"),
        });
    }
    let events = understand_request(request)?;
    if events.len() > MAX_REQUEST_EVENTS {
        return Err(RulesError::TooLong {
            request: request.trim().to_string(),
            what: format!("{} events", events.len()),
        });
    }
    Ok(events)
}

/// Splits a request into events, one per clause naming a known behaviour.
pub fn understand_request(request: &str) -> Result<Vec<Event>, RulesError> {
    let protected = protect_points(request);
    let mut events = understand(&protected)?;
    for e in &mut events {
        e.clause = e.clause.replace('\u{1f}', ",");
    }
    Ok(events)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn one(req: &str) -> (Behavior, String) {
        let e = understand_request(req).unwrap();
        assert_eq!(e.len(), 1, "{req}: {e:?}");
        (e[0].behaviour, e[0].params.to_string())
    }

    #[test]
    fn the_papers_vocabulary_with_ids() {
        assert_eq!(
            one("Vehicle 1 cuts in front of vehicle 2"),
            (Behavior::CutIn, "cutter=1 victim=2".into())
        );
        assert_eq!(
            one("vehicle 3 drives off the road"),
            (Behavior::OffRoad, "vehicle=3".into())
        );
        assert_eq!(
            one("vehicle 4 moves to the rightmost lane"),
            (Behavior::RightmostLane, "vehicle=4".into())
        );
        assert_eq!(
            one("vehicle 5 yields to vehicle 6"),
            (Behavior::Yield, "yielder=5 other=6".into())
        );
        assert_eq!(
            one("vehicle 7 keeps below 50 km/h"),
            (Behavior::SpeedLimit, "vehicle=7 limit=13.889".into())
        );
        assert_eq!(
            one("vehicle 8 reaches the target point (10.5, -3)"),
            (Behavior::TargetPoint, "vehicle=8 x=10.5 y=-3.0".into())
        );
        assert_eq!(one("no collisions").0, Behavior::NoCollisions);
        assert_eq!(
            one("vehicle 9 makes a left lane change"),
            (Behavior::LaneChangeLeft, "vehicle=9".into())
        );
        assert_eq!(
            one("car 9 changes lanes to the right"),
            (Behavior::LaneChangeRight, "vehicle=9".into())
        );
        assert_eq!(
            one("vehicle 10 follows vehicle 11 at 15 m"),
            (Behavior::Follow, "follower=10 leader=11 gap=15.0".into())
        );
        assert_eq!(
            one("vehicle 12 drives in reverse"),
            (Behavior::Reverse, "vehicle=12".into())
        );
        assert_eq!(
            one("vehicle 13 weaves left and right within its lane"),
            (Behavior::Weave, "vehicle=13".into())
        );
        assert_eq!(
            one("vehicle 14 stops within 3 s"),
            (Behavior::Stop, "vehicle=14 within=3.0".into())
        );
        assert_eq!(
            one("vehicle 15 crashes into vehicle 16"),
            (Behavior::Accident, "attacker=15 target=16".into())
        );
        assert_eq!(
            one("vehicle 2 turns right at the next junction"),
            (Behavior::TurnRight, "vehicle=2".into())
        );
        assert_eq!(
            one("vehicle 17 makes a left turn"),
            (Behavior::TurnLeft, "vehicle=17".into())
        );
        // A left lane change is not a left turn.
        assert_eq!(
            one("vehicle 9 makes a left lane change").0,
            Behavior::LaneChangeLeft
        );
    }

    #[test]
    fn a_composed_request_keeps_the_events_it_knows() {
        let req = "vehicle 109 moves to the rightmost lane, while vehicle 114 drives straight \
                   and vehicle 117 follows vehicle 114";
        // The planner itself needs every clause.
        assert!(understand_request(req).is_err());
        let (events, left) = understand_partly(req);
        let got: Vec<_> = events
            .iter()
            .map(|e| (e.behaviour, e.params.to_string()))
            .collect();
        assert_eq!(
            got,
            [
                (Behavior::RightmostLane, "vehicle=109".to_string()),
                (Behavior::Follow, "follower=117 leader=114".to_string())
            ]
        );
        assert_eq!(left.len(), 1);
        assert!(
            matches!(&left[0], RulesError::NotUnderstood { clause, .. } if clause == "vehicle 114 drives straight"),
            "{left:?}"
        );
    }

    #[test]
    fn conjunctions_split_into_events_and_the_subject_carries_over() {
        let e = understand_request(
            "vehicle 401 cuts in front of vehicle 399, vehicle 405 drives off the road",
        )
        .unwrap();
        let got: Vec<(Behavior, String)> = e
            .iter()
            .map(|e| (e.behaviour, e.params.to_string()))
            .collect();
        assert_eq!(
            got,
            vec![
                (Behavior::CutIn, "cutter=401 victim=399".into()),
                (Behavior::OffRoad, "vehicle=405".into())
            ]
        );
        let e = understand_request("vehicle 3 slows down and then stops").unwrap_err();
        assert!(matches!(e, RulesError::NotUnderstood { .. }), "{e}");
        let e = understand_request("vehicle 3 changes lanes to the left and then stops").unwrap();
        assert_eq!(e[1].params.to_string(), "vehicle=3");
    }

    #[test]
    fn what_it_cannot_plan_says_why_and_how_to_get_an_llm() {
        let e = understand_request("a bus driver sneezes")
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("DRIVESCRIPT_LLM_URL") && e.contains("cut_in"),
            "{e}"
        );
        let e = understand_request("vehicle 1 cuts in")
            .unwrap_err()
            .to_string();
        assert!(e.contains("two vehicle ids (cutter and victim)"), "{e}");
        let e = understand_request("vehicle 1 keeps below the limit")
            .unwrap_err()
            .to_string();
        assert!(e.contains("a speed with its unit"), "{e}");
    }

    #[test]
    fn composed_scripts_bind_params_reweight_and_keep_names_unique() {
        let e =
            understand_request("vehicle 2 cuts in front of vehicle 1, vehicle 2 follows vehicle 1")
                .unwrap();
        let t = vec![
            Tuning {
                weight: 2.0,
                margins: Params::numbers(&[("gap", 8.0)]),
            },
            Tuning::default(),
        ];
        let s = compose(&e, &t);
        assert!(!s.contains("param("), "{s}");
        assert!(s.contains("let a = agent(2);"), "{s}");
        assert!(s.contains("let gap_min = 8.0;"), "{s}");
        assert!(
            s.contains("term(\"no_contact\", collision_penalty(a, held, 0.5).sum(), 2.0 * 5.0)"),
            "{s}"
        );
        assert!(
            s.contains("term(\"starts_beside\", relu(1.5 - abs(fa.d.first())), 2.0)"),
            "{s}"
        );
        // A term with a tolerance keeps it, its weight scaled.
        let r = understand_request("vehicle 4 moves to the rightmost lane").unwrap();
        let s2 = compose(
            &r,
            &[Tuning {
                weight: 2.0,
                margins: Params::default(),
            }],
        );
        assert!(
            s2.contains("term(\"settled_in_rightmost_lane\", relu(abs(settle) - tol).mean(), 2.0 * 0.5, 0.25)"),
            "{s2}"
        );
        // The follow block's contact term is renamed, its weight untouched.
        assert!(
            s.contains("term(\"no_contact_2\", collision_penalty(a, held, 0.5).sum(), 5.0)"),
            "{s}"
        );
    }

    #[test]
    fn repairs_strengthen_failures_and_soften_implausible_successes() {
        let e = &understand_request("vehicle 3 drives off the road").unwrap()[0];
        let (t, why) = retune(e, &Tuning::default(), false);
        assert_eq!(t.weight, 2.0);
        assert_eq!(t.margins.number("distance"), Some(2.0));
        assert!(why.contains("distance 1 → 2"), "{why}");
        let (t2, _) = retune(e, &t, true);
        assert_eq!((t2.weight, t2.margins.number("distance")), (1.0, Some(2.0)));
        let mut t = Tuning::default();
        for _ in 0..10 {
            t = retune(e, &t, false).0;
        }
        assert_eq!((t.weight, t.margins.number("distance")), (16.0, Some(4.0)));
    }
}
