//! drivescript's YAML scenes: a straight or curved multi-lane road and a few agents, written by
//! hand in a few lines, or a full map (`map:`) as `drivescript convert` writes it. The format is
//! documented in docs/scene-formats.md ("YAML scenes").
//!
//! The road is built along a reference line, its right edge: it starts at `origin`, heads
//! `heading` degrees and is straight (`radius: 0`) or an arc (`radius > 0` bends left, `< 0`
//! right). Lane `k` (0 = rightmost) of road segment `j` has id `100 * (j + 1) + k`. Agents
//! either move along a lane (`lane`, `s`, `d`, `speed`, `accel`, optional `lane_change`) or
//! give explicit `states`.

use std::path::Path;

use serde::{Deserialize, Serialize};

use super::IoError;
use crate::geom::{FrenetPath, Point, Polygon, Polyline};
use crate::scene::{
    Agent, AgentState, AgentType, Lane, LaneType, Map, MapParts, RoadEdge, RoadEdgeKind, RoadLine,
    RoadLineKind, Scene, SceneError, SceneMeta, SourceFormat, StopLine, LANE_SPEED_LIMIT,
};

/// A YAML scene file.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct YamlScene {
    /// Scenario id (default: the file name).
    #[serde(default)]
    pub scenario_id: Option<String>,
    /// Seconds per step.
    #[serde(default = "default_dt")]
    pub dt: f64,
    /// Number of steps.
    #[serde(default = "default_steps")]
    pub steps: usize,
    /// Index of the current step.
    #[serde(default = "default_current")]
    pub current_step: usize,
    /// A generated road (give this or `map`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub road: Option<YamlRoad>,
    /// An explicit map (give this or `road`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub map: Option<YamlMap>,
    /// The agents.
    #[serde(default)]
    pub agents: Vec<YamlAgent>,
    /// The ego agent's id.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub ego: Option<i64>,
}

/// A list of `[x, y]` points.
pub type YamlPoints = Vec<[f64; 2]>;

/// An explicit map.
#[derive(Debug, Clone, Default, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct YamlMap {
    /// Lanes.
    #[serde(default)]
    pub lanes: Vec<YamlLane>,
    /// Road edges, road on their left.
    #[serde(default)]
    pub road_edges: Vec<YamlEdge>,
    /// Painted lines.
    #[serde(default)]
    pub road_lines: Vec<YamlRoadLine>,
    /// Crosswalk polygons.
    #[serde(default)]
    pub crosswalks: Vec<YamlPoints>,
    /// Stop lines and signs.
    #[serde(default)]
    pub stop_lines: Vec<YamlStopLine>,
    /// Speed bump polygons.
    #[serde(default)]
    pub speed_bumps: Vec<YamlPoints>,
    /// Drivable-area polygons.
    #[serde(default)]
    pub drivable_areas: Vec<YamlPoints>,
}

/// A lane of an explicit map.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct YamlLane {
    /// Lane id.
    pub id: i64,
    /// Centre line in the direction of travel.
    pub centerline: YamlPoints,
    /// Left boundary.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub left_boundary: Option<YamlPoints>,
    /// Right boundary.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub right_boundary: Option<YamlPoints>,
    /// Lane type.
    #[serde(rename = "type", default = "default_map_lane_type")]
    pub lane_type: LaneType,
    /// Speed limit, m/s.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub speed_limit: Option<f64>,
    /// Inside an intersection.
    #[serde(default, skip_serializing_if = "std::ops::Not::not")]
    pub intersection: bool,
    /// Predecessor lane ids.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub predecessors: Vec<i64>,
    /// Successor lane ids.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub successors: Vec<i64>,
    /// Same-direction left neighbours.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub left: Vec<i64>,
    /// Same-direction right neighbours.
    #[serde(default, skip_serializing_if = "Vec::is_empty")]
    pub right: Vec<i64>,
}

fn default_map_lane_type() -> LaneType {
    LaneType::SurfaceStreet
}

/// A road edge of an explicit map.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct YamlEdge {
    /// Edge kind.
    #[serde(default = "default_edge_kind")]
    pub kind: RoadEdgeKind,
    /// Points, road on the left.
    pub points: YamlPoints,
}

fn default_edge_kind() -> RoadEdgeKind {
    RoadEdgeKind::Boundary
}

/// A painted line of an explicit map.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct YamlRoadLine {
    /// Marking kind.
    pub kind: RoadLineKind,
    /// Yellow paint.
    #[serde(default)]
    pub yellow: bool,
    /// Points.
    pub points: YamlPoints,
}

/// A stop line of an explicit map.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct YamlStopLine {
    /// One point (a sign) or the line's ends.
    pub points: YamlPoints,
    /// Controlled lanes.
    #[serde(default)]
    pub lanes: Vec<i64>,
}

fn default_dt() -> f64 {
    0.1
}
fn default_steps() -> usize {
    91
}
fn default_current() -> usize {
    10
}

/// The road of a YAML scene.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct YamlRoad {
    /// Number of lanes, all driving the same way.
    pub lanes: usize,
    /// Lane width, metres.
    #[serde(default = "default_lane_width")]
    pub lane_width: f64,
    /// Length of the road, metres.
    pub length: f64,
    /// Lanes are cut into this many consecutive pieces (to give the lane graph successors).
    #[serde(default = "default_segments")]
    pub segments: usize,
    /// Radius of the reference line: 0 straight, > 0 bends left, < 0 bends right.
    #[serde(default)]
    pub radius: f64,
    /// Start of the reference line (the road's right edge).
    #[serde(default)]
    pub origin: [f64; 2],
    /// Initial heading, degrees.
    #[serde(default)]
    pub heading: f64,
    /// Speed limit, m/s.
    #[serde(default)]
    pub speed_limit: Option<f64>,
    /// `freeway` or `surface_street`.
    #[serde(default = "default_lane_type")]
    pub lane_type: LaneType,
}

/// The narrowest and widest lane a generated road may have, metres (real lanes are about 2.5-5 m;
/// the margins leave room for bicycle lanes and wide shoulders).
pub const MIN_LANE_WIDTH: f64 = 0.5;
/// See [`MIN_LANE_WIDTH`].
pub const MAX_LANE_WIDTH: f64 = 20.0;

fn default_lane_width() -> f64 {
    3.6
}
fn default_segments() -> usize {
    1
}
fn default_lane_type() -> LaneType {
    LaneType::Freeway
}

/// A scripted lane change.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct YamlLaneChange {
    /// Target lane index.
    pub to: usize,
    /// Start, seconds after the current step (negative: in the history).
    pub start: f64,
    /// Duration, seconds.
    #[serde(default = "default_lc_duration")]
    pub duration: f64,
}

fn default_lc_duration() -> f64 {
    3.0
}

/// The longest `lane_change.duration`: a lane change takes a few seconds; one of 1e308 s never
/// moved the agent off its lane, and said nothing.
pub const MAX_LANE_CHANGE_SECONDS: f64 = 60.0;

/// The most lane a generated road holds, metres (lanes × length): reading keeps about 400 KB
/// a lane-kilometre and sampling about 1.5 MB, so about 200 MB and 750 MB here (four lanes of
/// the longest road, 100 km, are 400 km).
pub const MAX_ROAD_LANE_METRES: f64 = 500_000.0;

/// The most lanes a generated road's map holds (lanes × segments): each is a lane of the
/// map, with its boundaries and links, about 1.5 KB.
pub const MAX_ROAD_LANES: usize = 10_000;

/// The shortest `lane_change.duration`, seconds: quicker, the agent jumps across its lane.
pub const MIN_LANE_CHANGE_SECONDS: f64 = 1.0;

/// Refuses a lane change that cannot be the one the file describes: a `duration` of 0, below
/// 0 or NaN moved the agent across in one step (the motion clamps it to a microsecond), and
/// one that starts after the last step or ends before the first changed nothing in the
/// scene; a NaN `start` was "step 0: state is not finite", naming no field.
fn lane_change_problem(lc: &YamlLaneChange, y: &YamlScene) -> Result<(), String> {
    let first = -(y.current_step as f64) * y.dt;
    let last = (y.steps as f64 - 1.0 - y.current_step as f64) * y.dt;
    let num = crate::geom::num;
    if !(lc.duration > 0.0 && lc.duration <= MAX_LANE_CHANGE_SECONDS) {
        return Err(format!(
            "lane_change.duration is {} s: must be more than 0 and at most \
             {MAX_LANE_CHANGE_SECONDS} s",
            num(lc.duration)
        ));
    }
    // Above 0 is not enough: 1e-300 s moved the agent across in one step, as 0 did.
    if lc.duration < MIN_LANE_CHANGE_SECONDS {
        return Err(format!(
            "lane_change.duration is {} s: a lane change that quick crosses the lane in less \
             than {MIN_LANE_CHANGE_SECONDS} s, a jump no road user makes; give at least \
             {MIN_LANE_CHANGE_SECONDS} s (a few seconds is usual)",
            num(lc.duration)
        ));
    }
    if !lc.start.is_finite() {
        return Err(format!(
            "lane_change.start is {}: must be a finite number of seconds after the current step",
            num(lc.start)
        ));
    }
    if lc.start >= last {
        return Err(format!(
            "lane_change.start is {} s, at or after the scene's last step ({} s after the \
             current step): the lane change would not happen in the scene",
            num(lc.start),
            num(last)
        ));
    }
    if lc.start + lc.duration <= first {
        return Err(format!(
            "lane_change ends {} s after the current step, before the scene's first step ({} \
             s): the agent is in lane {} throughout; give `lane: {}` instead",
            num(lc.start + lc.duration),
            num(first),
            lc.to,
            lc.to
        ));
    }
    Ok(())
}

/// An agent of a YAML scene.
#[derive(Debug, Clone, Deserialize, Serialize)]
#[serde(deny_unknown_fields)]
pub struct YamlAgent {
    /// Identifier.
    pub id: i64,
    /// `vehicle`, `pedestrian`, `cyclist` or `other`.
    #[serde(default = "default_agent_type", rename = "type")]
    pub agent_type: AgentType,
    /// Footprint length (default by type).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub length: Option<f64>,
    /// Footprint width (default by type).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub width: Option<f64>,
    /// Lane index at the current step (0 = rightmost).
    #[serde(default, skip_serializing_if = "is_zero_usize")]
    pub lane: usize,
    /// Distance along the road at the current step, metres.
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub s: f64,
    /// Lateral offset from the lane centre, metres (left positive).
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub d: f64,
    /// Speed at the current step, m/s (negative drives backwards).
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub speed: f64,
    /// Constant acceleration, m/s² (the agent stops rather than reverse).
    #[serde(default, skip_serializing_if = "is_zero_f64")]
    pub accel: f64,
    /// Optional scripted lane change.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub lane_change: Option<YamlLaneChange>,
    /// First valid step (default 0): agents that appear late.
    #[serde(default, skip_serializing_if = "is_zero_usize")]
    pub valid_from: usize,
    /// With an explicit `map`: the lane ids the agent drives along (consecutive lanes); `s` is
    /// measured from the start of the first, `d` from the centre line.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub route: Option<Vec<i64>>,
    /// Explicit states, one per step, replacing the motion fields: `[x, y, heading]` or
    /// `[x, y, heading, vx, vy]`, or `~` (null) where the agent is not observed.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub states: Option<Vec<Option<Vec<f64>>>>,
    /// A static obstacle (a parked car): it holds its current pose and no sampler moves it.
    #[serde(default, rename = "static", skip_serializing_if = "std::ops::Not::not")]
    pub is_static: bool,
}

/// The most a generated agent's `speed` may be, m/s (360 km/h).
const MAX_YAML_SPEED: f64 = 100.0;
/// The most a generated agent's `accel` may be, m/s² (5 g).
const MAX_YAML_ACCEL: f64 = 50.0;
/// The most a generated agent's `s` may be, m: ten times the longest road.
const MAX_MOTION_COORD: f64 = 1e6;
/// The most a generated agent's `d` may be, m: an offset across its lane, more than the
/// widest generated road's half (64 lanes of at most 20 m is 640 m across, but an agent that
/// far across is on another `lane`). `d: 1e6`, a kilometre beyond any road, was taken
/// without a word.
pub const MAX_LATERAL_OFFSET: f64 = 100.0;

fn is_zero_f64(v: &f64) -> bool {
    *v == 0.0
}
fn is_zero_usize(v: &usize) -> bool {
    *v == 0
}

fn default_agent_type() -> AgentType {
    AgentType::Vehicle
}

/// Default footprint (length, width) for an agent type.
pub fn default_size(t: AgentType) -> (f64, f64) {
    match t {
        AgentType::Vehicle => (4.6, 1.9),
        AgentType::Pedestrian => (0.6, 0.6),
        AgentType::Cyclist => (1.8, 0.7),
        AgentType::Other => (1.0, 1.0),
    }
}

/// Reads a YAML scene file.
pub fn read(path: &Path) -> Result<Scene, IoError> {
    let text = super::read_text(path)?;
    parse(path, &text)
}

/// The deepest flow nesting (`[`, `{`) a YAML scene may have; real scenes nest four deep.
pub const MAX_YAML_DEPTH: usize = 128;

/// What [`structure`] finds wrong with YAML text before it is parsed.
#[derive(Debug, PartialEq)]
enum Structure {
    /// The line of the first flow collection nested deeper than the limit: the YAML parser's
    /// time grows with the square of the depth (100,000 brackets took 36 s to refuse).
    TooDeep(usize),
    /// The line and text of the first tag (`!!str`, `!point`): serde reads a tagged scalar by
    /// the field's type whatever the tag says, so `id: !!str 1` was agent 1 while `id: "1"` was
    /// refused, and `!!int "1"` was "invalid type: integer `1`, expected i64".
    Tag(usize, String),
    /// The line and text of a top-level key given a second time, and the line of the first:
    /// serde said "duplicate field `steps`" at line 1, column 1 (the mapping's start) for a
    /// scene and named no line at all for a batch file.
    DuplicateKey(usize, String, usize),
    /// The line of a `---` that starts a second document: serde said only that more than one
    /// document "is not supported".
    SecondDocument(usize),
}

/// The first of [`Structure`]'s problems in `text`, if any. Brackets and `!` inside quotes,
/// comments and block scalars (`|`, `>`) do not count, nor a `!` inside a plain scalar (`wow !`
/// is text: a tag only starts a value) or at the start of an indented line (a plain scalar's
/// continuation may start with one).
fn structure(text: &str, max_depth: usize) -> Option<Structure> {
    let (mut depth, mut line) = (0usize, 1usize);
    let mut quote: Option<char> = None;
    let mut chars = text.char_indices().peekable();
    let mut prev = '\n';
    // The last character that is not a space or tab: a value starts after one of `:-[{,?`.
    let mut last = '\n';
    // The indentation of the line being read, and that of a line that opened a block scalar.
    let (mut indent, mut block) = (leading_spaces(text), None::<usize>);
    // Top-level keys of the document and their lines; whether anything but comments was read.
    let mut keys: std::collections::HashMap<String, usize> = Default::default();
    let mut content = false;
    if let Some(found) = line_start(text, 1, &mut keys, &mut content) {
        return Some(found);
    }
    while let Some((i, c)) = chars.next() {
        match (quote, c) {
            (_, '\n') => {
                line += 1;
                // Flow scalars may span lines, but a quote left open is the parser's to report.
                let mut next = i + 1;
                if let Some(parent) = block.take() {
                    // A block scalar's text is every following line that is blank or indented
                    // past the line that opened it.
                    loop {
                        let rest = &text[next..];
                        let n = leading_spaces(rest);
                        match rest[n..].chars().next() {
                            Some('\n') => {}
                            Some(_) if n > parent => {}
                            _ => break,
                        }
                        match rest.find('\n') {
                            Some(end) => next += end + 1,
                            None => next = text.len(),
                        }
                        line += 1;
                    }
                    while chars.next_if(|&(j, _)| j < next).is_some() {}
                }
                indent = leading_spaces(&text[next..]);
                if depth == 0 && quote.is_none() {
                    if let Some(found) = line_start(&text[next..], line, &mut keys, &mut content) {
                        return Some(found);
                    }
                }
            }
            (Some('"'), '\\') => {
                chars.next();
            }
            (Some(q), c) if c == q => quote = None,
            (Some(_), _) => {}
            // A quote opens a scalar only where a token starts (`O'Brien` is plain).
            (None, '"' | '\'') if prev.is_whitespace() || "[{,:-".contains(prev) => quote = Some(c),
            (None, '#') if prev.is_whitespace() => {
                while chars.next_if(|&(_, n)| n != '\n').is_some() {}
            }
            (None, '|' | '>') if depth == 0 && prev.is_whitespace() && ":-?".contains(last) => {
                block = Some(indent)
            }
            (None, '[' | '{') => {
                depth += 1;
                if depth > max_depth {
                    return Some(Structure::TooDeep(line));
                }
            }
            (None, ']' | '}') => depth = depth.saturating_sub(1),
            (None, '!')
                if (prev.is_whitespace() || "[{,".contains(prev))
                    && (":-[{?".contains(last)
                        || (last == ',' && depth > 0)
                        || prev == '\n' && depth == 0) =>
            {
                let tag: String = std::iter::once('!')
                    .chain(
                        text[i + 1..]
                            .chars()
                            .take_while(|n| !n.is_whitespace() && !",[]{}".contains(*n)),
                    )
                    .take(40)
                    .collect();
                return Some(Structure::Tag(line, tag));
            }
            _ => {}
        }
        if c != ' ' && c != '\t' {
            last = c;
        }
        prev = c;
    }
    None
}

/// What the start of a line outside any flow collection, quote or block scalar says: a `---`
/// after content starts a second document; `key:` at column 0 is a top-level key, refused
/// when given before. `rest` is the text from the line's start.
fn line_start(
    rest: &str,
    line: usize,
    keys: &mut std::collections::HashMap<String, usize>,
    content: &mut bool,
) -> Option<Structure> {
    let first = rest.split('\n').next().unwrap_or("");
    let first = first.strip_suffix('\r').unwrap_or(first);
    let marker = first
        .strip_prefix("---")
        .is_some_and(|t| t.is_empty() || t.starts_with([' ', '\t']));
    if marker {
        if *content {
            return Some(Structure::SecondDocument(line));
        }
        return None;
    }
    let body = first.trim_start();
    if !body.is_empty() && !body.starts_with('#') {
        *content = true;
    }
    if first.starts_with([' ', '\t', '-', '#', '"', '\'', '[', '{', '?', '%']) {
        return None;
    }
    let key = first
        .find(": ")
        .or_else(|| first.strip_suffix(':').map(|k| k.len()))
        .map(|end| &first[..end])
        .filter(|k| !k.is_empty() && !k.contains(" #"))?;
    // A map: a file of 100,000 distinct top-level keys compared each with all before it.
    match keys.entry(key.to_string()) {
        std::collections::hash_map::Entry::Occupied(first) => {
            Some(Structure::DuplicateKey(line, key.to_string(), *first.get()))
        }
        std::collections::hash_map::Entry::Vacant(v) => {
            v.insert(line);
            None
        }
    }
}

/// The spaces at the start of `s`.
fn leading_spaces(s: &str) -> usize {
    s.len() - s.trim_start_matches(' ').len()
}

/// The message for a tag [`structure`] found.
fn tag_message(tag: &str) -> String {
    format!(
        "YAML tags such as `{}` are not read: write the value itself (a number bare, text in \
         quotes); a tag does not change how drivescript reads a value",
        super::name::one_line(tag)
    )
}

/// The line and message of [`structure`]'s first problem in `text`, if any.
fn structure_error(text: &str) -> Option<(usize, String)> {
    match structure(text, MAX_YAML_DEPTH)? {
        Structure::TooDeep(line) => Some((line, too_deep_message())),
        Structure::Tag(line, tag) => Some((line, tag_message(&tag))),
        Structure::DuplicateKey(line, key, first) => Some((
            line,
            format!(
                "`{}` is given a second time (first on line {first}): give each key once",
                super::name::one_line(&key)
            ),
        )),
        Structure::SecondDocument(line) => Some((
            line,
            "a second YAML document starts here (`---`): the file must hold one".into(),
        )),
    }
}

/// Refuses YAML text (a batch or script test file) with flow collections nested past
/// [`MAX_YAML_DEPTH`], a tag, or aliases past [`MAX_YAML_EXPANDED_VALUES`]; the error is the
/// message to give, naming the line.
pub fn check_text(text: &str) -> Result<(), String> {
    match structure_error(text) {
        Some((line, message)) => Err(format!("line {line}: {message}")),
        None => check_aliases(text),
    }
}

fn too_deep_message() -> String {
    format!(
        "collections nested more than {MAX_YAML_DEPTH} deep: not a scene, batch or test file \
         (refused before parsing)"
    )
}

/// The most values (scalars and collections) a YAML document may expand to through its
/// aliases (`*name`) beyond one per byte of its text: 10 million values are hundreds of MB in
/// memory, far beyond any real scene, batch or test file.
pub const MAX_YAML_EXPANDED_VALUES: usize = 10_000_000;

/// Refuses YAML `text` whose aliases expand it past [`MAX_YAML_EXPANDED_VALUES`] values (or
/// one per byte of text, whichever is more), walking its values without keeping them: each
/// alias repeats its anchor's whole value, so aliases of aliases multiply (a 460 KB scene of
/// crosswalks that are one 2000-point polygon took 3.4 GB to read). Text with no `*` has no
/// alias and is not walked. The error is the message to give, naming the line where it can.
pub fn check_aliases(text: &str) -> Result<(), String> {
    use serde::de::DeserializeSeed;
    if !text.contains('*') {
        return Ok(());
    }
    let limit = MAX_YAML_EXPANDED_VALUES.max(text.len());
    let count = std::cell::Cell::new(0usize);
    for doc in serde_yaml::Deserializer::from_str(text) {
        if let Err(e) = (Budget {
            count: &count,
            limit,
        })
        .deserialize(doc)
        {
            // Only the budget's error is this check's to give: a syntax error is the
            // reader's own, with its own words.
            if count.get() > limit {
                return Err(match e.location() {
                    Some(l) => format!(
                        "line {}, column {}: {}",
                        l.line(),
                        l.column(),
                        super::without_position(&e.to_string(), l.line(), l.column())
                    ),
                    None => e.to_string(),
                });
            }
            return Ok(());
        }
    }
    Ok(())
}

/// Counts the values of a YAML document as serde walks it (aliases expanded), keeping none,
/// and stops past `limit`.
struct Budget<'a> {
    count: &'a std::cell::Cell<usize>,
    limit: usize,
}

impl Budget<'_> {
    fn take<E: serde::de::Error>(&self) -> Result<(), E> {
        self.count.set(self.count.get() + 1);
        if self.count.get() > self.limit {
            return Err(E::custom(format!(
                "its aliases (`*name`) expand it to more than {} values: far beyond a real \
                 file, so it is refused before it fills memory",
                self.limit
            )));
        }
        Ok(())
    }
    fn again(&self) -> Self {
        Budget {
            count: self.count,
            limit: self.limit,
        }
    }
}

impl<'de> serde::de::DeserializeSeed<'de> for Budget<'_> {
    type Value = ();
    fn deserialize<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_any(self)
    }
}

impl<'de> serde::de::Visitor<'de> for Budget<'_> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("any YAML value")
    }
    fn visit_bool<E: serde::de::Error>(self, _: bool) -> Result<(), E> {
        self.take()
    }
    fn visit_i64<E: serde::de::Error>(self, _: i64) -> Result<(), E> {
        self.take()
    }
    fn visit_u64<E: serde::de::Error>(self, _: u64) -> Result<(), E> {
        self.take()
    }
    fn visit_i128<E: serde::de::Error>(self, _: i128) -> Result<(), E> {
        self.take()
    }
    fn visit_u128<E: serde::de::Error>(self, _: u128) -> Result<(), E> {
        self.take()
    }
    fn visit_f64<E: serde::de::Error>(self, _: f64) -> Result<(), E> {
        self.take()
    }
    fn visit_str<E: serde::de::Error>(self, _: &str) -> Result<(), E> {
        self.take()
    }
    fn visit_unit<E: serde::de::Error>(self) -> Result<(), E> {
        self.take()
    }
    fn visit_none<E: serde::de::Error>(self) -> Result<(), E> {
        self.take()
    }
    fn visit_some<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        serde::de::DeserializeSeed::deserialize(self, d)
    }
    fn visit_newtype_struct<D: serde::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        serde::de::DeserializeSeed::deserialize(self, d)
    }
    fn visit_seq<A: serde::de::SeqAccess<'de>>(self, mut seq: A) -> Result<(), A::Error> {
        self.take()?;
        while seq.next_element_seed(self.again())?.is_some() {}
        Ok(())
    }
    fn visit_map<A: serde::de::MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        self.take()?;
        while map.next_key_seed(self.again())?.is_some() {
            map.next_value_seed(self.again())?;
        }
        Ok(())
    }
    fn visit_enum<A: serde::de::EnumAccess<'de>>(self, data: A) -> Result<(), A::Error> {
        // A tagged value (`!tag value`): the tag, then its value.
        use serde::de::VariantAccess;
        let ((), v) = data.variant_seed(self.again())?;
        v.newtype_variant_seed(self)
    }
}

/// Parses YAML scene text (`path` is used for messages and metadata).
pub fn parse(path: &Path, text: &str) -> Result<Scene, IoError> {
    if let Some((line, message)) = structure_error(text) {
        return Err(IoError::invalid(path, format!("line {line}"), message));
    }
    check_aliases(text).map_err(|m| IoError::invalid(path, "aliases", m))?;
    let y: YamlScene = serde_yaml::from_str(text).map_err(|e| match e.location() {
        Some(l) => IoError::invalid(
            path,
            format!("line {}, column {}", l.line(), l.column()),
            super::without_position(&e.to_string(), l.line(), l.column()),
        ),
        None => IoError::invalid(path, "document", e.to_string()),
    })?;
    build(path, &y)
}

fn reference_line(r: &YamlRoad) -> Polyline {
    let n = (r.length / 1.0).ceil().max(1.0) as usize + 1;
    let h0 = r.heading.to_radians();
    let o = Point::new(r.origin[0], r.origin[1]);
    let pts = (0..n).map(|k| {
        let s = r.length * k as f64 / (n - 1) as f64;
        if r.radius == 0.0 {
            o + Point::new(h0.cos(), h0.sin()) * s
        } else {
            let a = s / r.radius;
            // Arc from the origin with curvature 1/radius, in the road's local frame.
            let local = Point::new(r.radius * a.sin(), r.radius * (1.0 - a.cos()));
            o + Point::new(
                local.x * h0.cos() - local.y * h0.sin(),
                local.x * h0.sin() + local.y * h0.cos(),
            )
        }
    });
    Polyline::new(pts).expect("a road of positive length")
}

fn build(path: &Path, y: &YamlScene) -> Result<Scene, IoError> {
    let bad = |loc: String, msg: String| IoError::invalid(path, loc, msg);
    if y.steps > super::MAX_STEPS {
        return Err(bad(
            "steps".into(),
            format!(
                "{} steps is implausible (limit {})",
                y.steps,
                super::MAX_STEPS
            ),
        ));
    }
    super::check_states(path, "agents", y.agents.len(), y.steps)?;
    if y.steps == 0 || y.current_step >= y.steps {
        return Err(bad(
            "current_step".into(),
            format!(
                "current_step {} must be below steps {}",
                y.current_step, y.steps
            ),
        ));
    }
    let (parts, road) = match (&y.road, &y.map) {
        (Some(r), None) => {
            let (parts, reference) = road_parts(path, r)?;
            (parts, Some((r, reference)))
        }
        (None, Some(m)) => (explicit_parts(path, m)?, None),
        _ => {
            return Err(bad(
                "document".into(),
                "give exactly one of `road` and `map`".into(),
            ))
        }
    };
    // An explicit map's centre line drawn out and back loaded without a word (its length,
    // and every path along it, read as the sum of both ways), where WOMD and GPUDrive
    // scenes are warned of it.
    let turning_back = if road.is_none() {
        super::turning_back_warning(&parts.lanes)
    } else {
        None
    };
    let map = Map::new(parts).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        location: "map".into(),
        error: e,
    })?;

    let mut agents = Vec::new();
    let mut off_road = Vec::new();
    for (i, a) in y.agents.iter().enumerate() {
        let loc = format!("agents[{i}] (id {})", a.id);
        let (dl, dw) = default_size(a.agent_type);
        let (length, width) = (a.length.unwrap_or(dl), a.width.unwrap_or(dw));
        // Motion fields beside explicit states were dropped without a word (a `speed: 30`
        // that changed nothing); so was a `lane` beside a `route`, which names the lanes.
        let ignored: Vec<&str> = if a.states.is_some() {
            [
                ("lane", a.lane != 0),
                ("s", a.s != 0.0),
                ("d", a.d != 0.0),
                ("speed", a.speed != 0.0),
                ("accel", a.accel != 0.0),
                ("lane_change", a.lane_change.is_some()),
                ("route", a.route.is_some()),
            ]
            .iter()
            .filter(|(_, given)| *given)
            .map(|(name, _)| *name)
            .collect()
        } else if a.route.is_some() && a.lane != 0 {
            vec!["lane"]
        } else {
            Vec::new()
        };
        if !ignored.is_empty() {
            return Err(bad(
                loc,
                format!(
                    "{} would be ignored: {} the agent's motion; remove {}",
                    ignored
                        .iter()
                        .map(|n| format!("`{n}`"))
                        .collect::<Vec<_>>()
                        .join(", "),
                    if a.states.is_some() {
                        "explicit `states` give"
                    } else {
                        "a `route` names the lanes of"
                    },
                    if ignored.len() == 1 { "it" } else { "them" }
                ),
            ));
        }
        // A motion field far out of range came out as "step 0: implausible position
        // (-5e307, 1.8)", naming neither the field nor what it may be.
        for (field, v, max, unit) in [
            ("s", a.s, MAX_MOTION_COORD, "m"),
            ("d", a.d, MAX_LATERAL_OFFSET, "m"),
            ("speed", a.speed, MAX_YAML_SPEED, "m/s"),
            ("accel", a.accel, MAX_YAML_ACCEL, "m/s²"),
        ] {
            if !(v.abs() <= max) {
                return Err(bad(
                    loc,
                    format!(
                        "{field} is {} {unit}: must be within ±{} {unit}{}",
                        crate::geom::num(v),
                        crate::geom::num(max),
                        if field == "d" {
                            " of the lane's centre (an agent on another lane: give its `lane` \
                             or `route`, or explicit `states`)"
                        } else {
                            ""
                        }
                    ),
                ));
            }
        }
        // A static agent holds its first observed pose: with a speed, an acceleration or a
        // lane change that pose is not the one at `s`, so `{static: true, s: 5, speed: 10}`
        // stood at s = -5 for the whole scene, without a word.
        if a.is_static && a.states.is_none() {
            let moving: Vec<&str> = [
                ("speed", a.speed != 0.0),
                ("accel", a.accel != 0.0),
                ("lane_change", a.lane_change.is_some()),
            ]
            .iter()
            .filter(|(_, given)| *given)
            .map(|(name, _)| *name)
            .collect();
            if !moving.is_empty() {
                return Err(bad(
                    loc,
                    format!(
                        "{} would be ignored: a `static` agent stands still at its pose at `s`; \
                         remove {}",
                        moving
                            .iter()
                            .map(|n| format!("`{n}`"))
                            .collect::<Vec<_>>()
                            .join(", "),
                        if moving.len() == 1 { "it" } else { "them" }
                    ),
                ));
            }
        }
        if let Some(lc) = &a.lane_change {
            lane_change_problem(lc, y).map_err(|m| bad(loc.clone(), m))?;
        }
        let mut states = if let Some(explicit) = &a.states {
            if explicit.len() != y.steps {
                return Err(bad(
                    loc,
                    format!("{} states for {} steps", explicit.len(), y.steps),
                ));
            }
            explicit_states(explicit, y.dt).map_err(|(k, m)| bad(format!("{loc} state {k}"), m))?
        } else {
            match (&road, &a.route) {
                (Some((r, reference)), None) => {
                    if a.lane >= r.lanes || a.lane_change.as_ref().is_some_and(|c| c.to >= r.lanes)
                    {
                        return Err(bad(
                            loc,
                            format!("lane index out of range: the road has {} lanes", r.lanes),
                        ));
                    }
                    if let Some(lc) = a.lane_change.as_ref().filter(|c| c.to == a.lane) {
                        return Err(bad(
                            loc,
                            format!(
                                "lane_change.to is {}, the agent's own lane: a lane change goes \
                                 to another lane (leave lane_change out to keep the lane)",
                                lc.to
                            ),
                        ));
                    }
                    off_road.extend(leaves_reference(a, y, r.length));
                    lane_motion(a, y, reference, r.lane_width)
                }
                (None, Some(route)) => {
                    if a.lane_change.is_some() {
                        return Err(bad(
                            loc,
                            "lane_change needs a generated `road`; give a `route` per lane instead"
                                .into(),
                        ));
                    }
                    let reference = route_path(&map, route).map_err(|m| bad(loc.clone(), m))?;
                    off_road.extend(leaves_reference(a, y, reference.length()));
                    lane_motion(a, y, &reference, 0.0)
                }
                (Some(_), Some(_)) => {
                    return Err(bad(
                        loc,
                        "`route` is for explicit maps; on a generated road use `lane`".into(),
                    ))
                }
                (None, None) => {
                    return Err(bad(
                        loc,
                        "with an explicit `map`, agents need a `route` or explicit `states`".into(),
                    ))
                }
            }
        };
        if a.valid_from >= y.steps {
            return Err(bad(
                loc,
                format!(
                    "valid_from {} must be below steps {}",
                    a.valid_from, y.steps
                ),
            ));
        }
        for s in states.iter_mut().take(a.valid_from) {
            *s = AgentState::INVALID;
        }
        if a.is_static && a.states.is_none() {
            // It holds its first observed pose, standing still. Explicit states are kept as
            // written: `convert` writes a recorded static object's (AV2's jitter by
            // millimetres, and its unobserved steps), and filling them with the first pose
            // moved it and made it present where it was not observed.
            if let Some(first) = states.iter().find(|s| s.valid).copied() {
                for s in states.iter_mut().skip(a.valid_from) {
                    *s = AgentState {
                        vx: 0.0,
                        vy: 0.0,
                        ..first
                    };
                }
            }
        }
        agents.push(Agent {
            id: a.id,
            agent_type: a.agent_type,
            length,
            width,
            states,
            is_static: a.is_static,
        });
    }
    let meta = SceneMeta {
        source_format: SourceFormat::Yaml,
        source_file: path.display().to_string(),
        scenario_id: y
            .scenario_id
            .clone()
            .unwrap_or_else(|| super::file_stem(path)),
        dt: y.dt,
        current_step: y.current_step,
        ego: y.ego,
        warnings: (!off_road.is_empty())
            .then(|| {
                format!(
                    "generated agents whose states leave the road or route they are placed on \
                     (the map ends there): {}",
                    super::first_few(&off_road)
                )
            })
            .into_iter()
            .chain(turning_back)
            .collect(),
    };
    Scene::recorded(meta, map, agents).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        // The key of the file the fault is under.
        location: match &e {
            SceneError::ScenarioId { .. } | SceneError::ScenarioIdTooLong { .. } => "scenario_id",
            SceneError::BadDt(_) | SceneError::RecordedDt(_) => "dt",
            SceneError::CurrentStep { .. } => "current_step",
            SceneError::DuplicateLane(_) | SceneError::UnknownLane(_) => "map",
            // Scene::new checks only the ego's id against the agents.
            SceneError::UnknownAgent(_) => "ego",
            _ => "agents",
        }
        .into(),
        error: e,
    })
}

/// The map of a generated road, and the road's reference line (its right edge).
fn road_parts(path: &Path, r: &YamlRoad) -> Result<(MapParts, FrenetPath), IoError> {
    let bad = |loc: &str, msg: String| IoError::invalid(path, loc, msg);
    if r.lanes == 0 || r.segments == 0 {
        return Err(bad("road", "lanes and segments must be at least 1".into()));
    }
    if !(r.length.is_finite() && r.length > 0.0) {
        return Err(bad("road", "length must be positive".into()));
    }
    // A width no road has (1e-9 m, 40 m) is a typo or a unit mix-up, not a scene: accepted, it
    // gives lanes that every car overlaps or that no car is ever "in".
    if !(MIN_LANE_WIDTH..=MAX_LANE_WIDTH).contains(&r.lane_width) {
        return Err(bad(
            "road.lane_width",
            format!(
                "{} m is not a lane width: it must lie in {MIN_LANE_WIDTH}..={MAX_LANE_WIDTH} m",
                crate::geom::num(r.lane_width)
            ),
        ));
    }
    if let Some(v) = r.speed_limit.filter(|v| !LANE_SPEED_LIMIT.contains(v)) {
        return Err(bad(
            "road.speed_limit",
            format!(
                "{} m/s is not a speed limit: it must be more than 0 and at most {} m/s",
                crate::geom::num(v),
                LANE_SPEED_LIMIT.end()
            ),
        ));
    }
    // One message for the three limits said "at most 100 km long" of a 0.5 m road whose
    // one segment was the fault, and named no value.
    if r.length > 100_000.0 {
        return Err(bad(
            "road.length",
            format!(
                "{} m: a road is at most 100 km (100000 m) long",
                crate::geom::num(r.length)
            ),
        ));
    }
    if r.lanes > 64 {
        return Err(bad(
            "road.lanes",
            format!("{}: a road has at most 64 lanes", r.lanes),
        ));
    }
    if r.segments as f64 > r.length {
        return Err(bad(
            "road.segments",
            format!(
                "{} segments on a road {} m long: a segment is at least 1 m long",
                r.segments,
                crate::geom::num(r.length)
            ),
        ));
    }
    // Each within its range is not enough: 64 lanes of a 100-km road (a 200-byte file) took
    // 1.9 GB and 9 s to read, and in 100,000 segments (6.4 million lanes) 9.3 GB and a minute.
    let lane_metres = r.lanes as f64 * r.length;
    if lane_metres > MAX_ROAD_LANE_METRES {
        return Err(bad(
            "road",
            format!(
                "{} lanes of {} m are {} km of lane: a generated road holds at most {} km \
                 (fewer lanes, or a shorter road)",
                r.lanes,
                crate::geom::num(r.length),
                crate::geom::num((lane_metres / 1000.0).round()),
                crate::geom::num(MAX_ROAD_LANE_METRES / 1000.0)
            ),
        ));
    }
    let lane_count = r.lanes.saturating_mul(r.segments);
    if lane_count > MAX_ROAD_LANES {
        return Err(bad(
            "road",
            format!(
                "{} lanes in {} segments are {lane_count} lanes of the map: a generated road \
                 holds at most {MAX_ROAD_LANES} (fewer segments)",
                r.lanes, r.segments
            ),
        ));
    }
    // A NaN heading made a road of NaN points, which panicked where the line was built; one
    // of 1e300 degrees points nowhere in particular (its sine keeps no digits).
    if !(r.heading.is_finite() && r.heading.abs() <= 360.0) {
        return Err(bad(
            "road.heading",
            format!(
                "{} is not a heading: it must lie in -360..=360 degrees",
                crate::geom::num(r.heading)
            ),
        ));
    }
    let max_offset = r.lanes as f64 * r.lane_width;
    // NaN and infinities were told that "|radius| must exceed the road width".
    if !r.radius.is_finite() {
        return Err(bad(
            "road.radius",
            format!(
                "{} is not a radius: give 0 for a straight road or a number of metres",
                crate::geom::num(r.radius)
            ),
        ));
    }
    if r.radius != 0.0 && r.radius.abs() <= max_offset + 1.0 {
        return Err(bad(
            "road.radius",
            format!("|radius| must exceed the road width ({max_offset} m)"),
        ));
    }
    // Past a full turn the road runs over itself: lanes cross lanes, and cars on their centre
    // lines read as off the road (a 400 m road at radius 50 was accepted and scored so).
    let turn = 2.0 * std::f64::consts::PI * r.radius.abs();
    if r.radius != 0.0 && r.length > turn {
        return Err(bad(
            "road.radius",
            format!(
                "a road of {} m at radius {} winds {:.2} times round and runs over itself: give \
                 a length of at most 2π·|radius| ({} m) or a larger radius",
                crate::geom::num(r.length),
                crate::geom::num(r.radius),
                r.length / turn,
                crate::geom::num((turn * 10.0).floor() / 10.0)
            ),
        ));
    }
    let reach = r.length + max_offset;
    if !(r.origin[0].is_finite() && r.origin[1].is_finite())
        || r.origin[0].abs() + reach > crate::geom::MAX_COORD
        || r.origin[1].abs() + reach > crate::geom::MAX_COORD
    {
        return Err(bad(
            "road.origin".into(),
            format!(
                "({}, {}): the road must lie within {:e} m of the origin",
                crate::geom::num(r.origin[0]),
                crate::geom::num(r.origin[1]),
                crate::geom::MAX_COORD
            ),
        ));
    }
    let reference = FrenetPath::new(reference_line(r));
    let w = r.lane_width;
    let offset_line = |d: f64, s0: f64, s1: f64| {
        let n = ((s1 - s0) / 1.0).ceil().max(1.0) as usize + 1;
        Polyline::new(
            (0..n).map(|k| reference.to_cartesian(s0 + (s1 - s0) * k as f64 / (n - 1) as f64, d)),
        )
        .expect("positive length")
    };
    let mut parts = MapParts::default();
    let seg_len = r.length / r.segments as f64;
    let lane_id = |j: usize, k: usize| 100 * (j as i64 + 1) + k as i64;
    for j in 0..r.segments {
        let (s0, s1) = (j as f64 * seg_len, (j + 1) as f64 * seg_len);
        for k in 0..r.lanes {
            let mut lane = Lane::new(lane_id(j, k), offset_line((k as f64 + 0.5) * w, s0, s1));
            lane.left_boundary = Some(offset_line((k + 1) as f64 * w, s0, s1));
            lane.right_boundary = Some(offset_line(k as f64 * w, s0, s1));
            lane.lane_type = r.lane_type;
            lane.speed_limit = r.speed_limit;
            if j > 0 {
                lane.predecessors.push(lane_id(j - 1, k));
            }
            if j + 1 < r.segments {
                lane.successors.push(lane_id(j + 1, k));
            }
            if k + 1 < r.lanes {
                lane.left_neighbors.push(lane_id(j, k + 1));
            }
            if k > 0 {
                lane.right_neighbors.push(lane_id(j, k - 1));
            }
            if let Some(s) = lane.surface() {
                parts.drivable_areas.push(s);
            }
            parts.lanes.push(lane);
        }
    }
    parts.road_edges.push(RoadEdge::new(
        RoadEdgeKind::Boundary,
        offset_line(0.0, 0.0, r.length),
    ));
    parts.road_edges.push(RoadEdge::new(
        RoadEdgeKind::Boundary,
        offset_line(max_offset, 0.0, r.length).reversed(),
    ));
    for k in 1..r.lanes {
        parts.road_lines.push(RoadLine {
            kind: RoadLineKind::Broken,
            yellow: false,
            line: offset_line(k as f64 * w, 0.0, r.length),
        });
    }
    Ok((parts, reference))
}

fn to_points(v: &[[f64; 2]]) -> impl Iterator<Item = Point> + '_ {
    v.iter().map(|p| Point::new(p[0], p[1]))
}

fn explicit_parts(path: &Path, m: &YamlMap) -> Result<MapParts, IoError> {
    let line = |loc: String, v: &[[f64; 2]]| {
        Polyline::new(to_points(v)).map_err(|e| IoError::invalid(path, loc, e.to_string()))
    };
    let poly = |loc: String, v: &[[f64; 2]]| {
        Polygon::new(to_points(v)).map_err(|e| IoError::invalid(path, loc, e.to_string()))
    };
    let mut parts = MapParts::default();
    let lane_ids: std::collections::HashSet<i64> = m.lanes.iter().map(|l| l.id).collect();
    for (i, l) in m.lanes.iter().enumerate() {
        let loc = |f: &str| format!("map.lanes[{i}] (id {}).{f}", l.id);
        // A hand-written map's slips: the graph dropped a lane that follows itself, and took
        // a lane on both sides as both, without a word.
        for (field, ids) in [
            ("predecessors", &l.predecessors),
            ("successors", &l.successors),
            ("left", &l.left),
            ("right", &l.right),
        ] {
            if ids.contains(&l.id) {
                return Err(IoError::invalid(
                    path,
                    loc(field),
                    format!("names lane {} itself", l.id),
                ));
            }
            // A mistyped id (`successors: [99]`) was dropped from the graph without a word,
            // and the lane ended there. (A map written by drivescript names only its lanes.)
            if let Some(missing) = ids.iter().find(|id| !lane_ids.contains(id)) {
                return Err(IoError::invalid(
                    path,
                    loc(field),
                    format!("names lane {missing}, which is not in the map"),
                ));
            }
        }
        if let Some(both) = l.left.iter().find(|id| l.right.contains(id)) {
            return Err(IoError::invalid(
                path,
                loc("right"),
                format!("lane {both} is in both left and right: a neighbour lies on one side"),
            ));
        }
        let mut lane = Lane::new(l.id, line(loc("centerline"), &l.centerline)?);
        lane.left_boundary = l
            .left_boundary
            .as_deref()
            .map(|b| line(loc("left_boundary"), b))
            .transpose()?;
        lane.right_boundary = l
            .right_boundary
            .as_deref()
            .map(|b| line(loc("right_boundary"), b))
            .transpose()?;
        // A boundary on the wrong side of its centre line loaded without a word: the lane's
        // surface and the road edges built from it turn inside out. Lanes too short to have a
        // direction are not judged (a real map converted to YAML holds some).
        let centre = FrenetPath::new(lane.centerline.clone());
        let judged = lane.centerline.length() >= crate::scene::MIN_JUDGED_LENGTH;
        for (field, b, sign, side, other) in [
            ("left_boundary", &lane.left_boundary, 1.0, "left", "right"),
            (
                "right_boundary",
                &lane.right_boundary,
                -1.0,
                "right",
                "left",
            ),
        ] {
            let Some(b) = b.as_ref().filter(|_| judged) else {
                continue;
            };
            let pts = b.points();
            let mean = pts.iter().map(|p| centre.project(*p).d).sum::<f64>() / pts.len() as f64;
            if mean * sign < -0.05 {
                return Err(IoError::invalid(
                    path,
                    loc(field),
                    format!(
                        "lies {other} of the centre line ({} m on average): a {side} boundary \
                         lies on the {side} in the direction of travel (are the two swapped, or \
                         the centre line reversed?)",
                        crate::geom::num((mean.abs() * 100.0).round() / 100.0),
                    ),
                ));
            }
        }
        lane.lane_type = l.lane_type;
        lane.speed_limit = l.speed_limit;
        lane.is_intersection = l.intersection;
        lane.predecessors = l.predecessors.clone();
        lane.successors = l.successors.clone();
        lane.left_neighbors = l.left.clone();
        lane.right_neighbors = l.right.clone();
        parts.lanes.push(lane);
    }
    // A link to a lane far from the end was kept, and a path along it jumped (206 m in the
    // report); routes were checked, links not.
    if let Some(f) = crate::scene::far_links(&parts.lanes).first() {
        let i = m.lanes.iter().position(|l| l.id == f.lane).unwrap_or(0);
        let (field, from, to) = if f.successor {
            ("successors", f.lane, f.other)
        } else {
            ("predecessors", f.other, f.lane)
        };
        return Err(IoError::invalid(
            path,
            format!("map.lanes[{i}] (id {}).{field}", f.lane),
            format!(
                "names lane {}, but lane {to} starts {} m from the end of lane {from} (at most \
                 {} m: a path along the link would jump the gap)",
                f.other,
                crate::geom::num((f.gap * 100.0).round() / 100.0),
                crate::scene::LINK_GAP
            ),
        ));
    }
    for (i, e) in m.road_edges.iter().enumerate() {
        parts.road_edges.push(RoadEdge::new(
            e.kind,
            line(format!("map.road_edges[{i}]"), &e.points)?,
        ));
    }
    for (i, l) in m.road_lines.iter().enumerate() {
        parts.road_lines.push(RoadLine {
            kind: l.kind,
            yellow: l.yellow,
            line: line(format!("map.road_lines[{i}]"), &l.points)?,
        });
    }
    for (i, c) in m.crosswalks.iter().enumerate() {
        parts
            .crosswalks
            .push(poly(format!("map.crosswalks[{i}]"), c)?);
    }
    for (i, c) in m.speed_bumps.iter().enumerate() {
        parts
            .speed_bumps
            .push(poly(format!("map.speed_bumps[{i}]"), c)?);
    }
    for (i, c) in m.drivable_areas.iter().enumerate() {
        parts
            .drivable_areas
            .push(poly(format!("map.drivable_areas[{i}]"), c)?);
    }
    for (i, s) in m.stop_lines.iter().enumerate() {
        if s.points.is_empty() || s.points.iter().flatten().any(|v| !v.is_finite()) {
            return Err(IoError::invalid(
                path,
                format!("map.stop_lines[{i}]"),
                "needs finite points",
            ));
        }
        parts.stop_lines.push(StopLine {
            points: to_points(&s.points).collect(),
            lanes: s.lanes.clone(),
        });
    }
    Ok(parts)
}

fn pts_out(pts: &[Point]) -> YamlPoints {
    pts.iter().map(|p| [p.x, p.y]).collect()
}

/// The whole scene (map and every agent's states) as a YAML document that [`parse`] reads
/// back to the same scene, headed by a comment naming the file it was read from.
pub fn to_yaml(scene: &Scene) -> String {
    format!(
        "# drivescript scene converted from {} ({})\n{}",
        scene.meta.source_file,
        scene.meta.source_format.name(),
        yaml_document(scene)
    )
}

/// [`to_yaml`] without its header: the same for the same scene from any file or format.
pub fn yaml_document(scene: &Scene) -> String {
    let g = scene.map.graph();
    let map = YamlMap {
        lanes: scene
            .map
            .lanes()
            .iter()
            .map(|l| YamlLane {
                id: l.id,
                centerline: pts_out(l.centerline.points()),
                left_boundary: l.left_boundary.as_ref().map(|b| pts_out(b.points())),
                right_boundary: l.right_boundary.as_ref().map(|b| pts_out(b.points())),
                lane_type: l.lane_type,
                speed_limit: l.speed_limit,
                intersection: l.is_intersection,
                predecessors: g.predecessors(l.id).to_vec(),
                successors: g.successors(l.id).to_vec(),
                left: g.left_neighbors(l.id).to_vec(),
                right: g.right_neighbors(l.id).to_vec(),
            })
            .collect(),
        road_edges: scene
            .map
            .road_edges()
            .iter()
            .map(|e| YamlEdge {
                kind: e.kind,
                points: pts_out(e.line().points()),
            })
            .collect(),
        road_lines: scene
            .map
            .road_lines()
            .iter()
            .map(|l| YamlRoadLine {
                kind: l.kind,
                yellow: l.yellow,
                points: pts_out(l.line.points()),
            })
            .collect(),
        crosswalks: scene
            .map
            .crosswalks()
            .iter()
            .map(|p| pts_out(p.points()))
            .collect(),
        stop_lines: scene
            .map
            .stop_lines()
            .iter()
            .map(|s| YamlStopLine {
                points: pts_out(&s.points),
                lanes: s.lanes.clone(),
            })
            .collect(),
        speed_bumps: scene
            .map
            .speed_bumps()
            .iter()
            .map(|p| pts_out(p.points()))
            .collect(),
        drivable_areas: scene
            .map
            .drivable_areas()
            .iter()
            .map(|p| pts_out(p.points()))
            .collect(),
    };
    let agents = scene
        .agents
        .iter()
        .map(|a| YamlAgent {
            id: a.id,
            agent_type: a.agent_type,
            length: Some(a.length),
            width: Some(a.width),
            lane: 0,
            s: 0.0,
            d: 0.0,
            speed: 0.0,
            accel: 0.0,
            lane_change: None,
            valid_from: 0,
            route: None,
            is_static: a.is_static,
            states: Some(
                a.states
                    .iter()
                    .map(|s| s.valid.then(|| vec![s.x, s.y, s.heading, s.vx, s.vy]))
                    .collect(),
            ),
        })
        .collect();
    let doc = YamlScene {
        scenario_id: Some(scene.meta.scenario_id.clone()),
        dt: scene.meta.dt,
        steps: scene.num_steps(),
        current_step: scene.meta.current_step,
        road: None,
        map: Some(map),
        agents,
        ego: scene.meta.ego,
    };
    serde_yaml::to_string(&doc).expect("scenes serialise to YAML")
}

fn explicit_states(xyh: &[Option<Vec<f64>>], dt: f64) -> Result<Vec<AgentState>, (usize, String)> {
    let n = xyh.len();
    for (k, s) in xyh.iter().enumerate() {
        if let Some(v) = s {
            if v.len() != 3 && v.len() != 5 {
                return Err((
                    k,
                    format!(
                        "expected [x, y, heading] or [x, y, heading, vx, vy], got {} numbers",
                        v.len()
                    ),
                ));
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err((k, "values must be finite".into()));
            }
        }
    }
    Ok((0..n)
        .map(|k| {
            let Some(v) = &xyh[k] else {
                return AgentState::INVALID;
            };
            let (vx, vy) = if v.len() == 5 {
                (v[3], v[4])
            } else {
                // Velocity from neighbouring valid states.
                let lo = if k > 0 && xyh[k - 1].is_some() {
                    k - 1
                } else {
                    k
                };
                let hi = if k + 1 < n && xyh[k + 1].is_some() {
                    k + 1
                } else {
                    k
                };
                if hi > lo {
                    let (a, b) = (
                        xyh[lo].as_ref().expect("valid"),
                        xyh[hi].as_ref().expect("valid"),
                    );
                    let span = (hi - lo) as f64 * dt;
                    ((b[0] - a[0]) / span, (b[1] - a[1]) / span)
                } else {
                    (0.0, 0.0)
                }
            };
            AgentState {
                x: v[0],
                y: v[1],
                heading: v[2],
                vx,
                vy,
                valid: true,
            }
        })
        .collect())
}

/// The centre lines of `route`'s lanes joined into one path.
fn route_path(map: &Map, route: &[i64]) -> Result<FrenetPath, String> {
    if route.is_empty() {
        return Err("route is empty".into());
    }
    let mut pts = Vec::new();
    for (k, id) in route.iter().enumerate() {
        let lane = map
            .lane(*id)
            .ok_or_else(|| format!("route lane {id} is not in the map"))?;
        if k > 0 && !map.graph().successors(route[k - 1]).contains(id) {
            return Err(format!(
                "route lane {id} does not follow lane {}",
                route[k - 1]
            ));
        }
        pts.extend_from_slice(lane.centerline.points());
    }
    Polyline::new(pts)
        .map(FrenetPath::new)
        .map_err(|e| e.to_string())
}

/// States along `reference` at lateral offset `(lane + 0.5) · w + d` (with `w = 0` along a
/// route's centre line).
/// A generated agent's arc length along its reference at step `k`: constant acceleration
/// until the speed reaches zero, then standing still.
fn s_at(a: &YamlAgent, y: &YamlScene, k: usize) -> f64 {
    let tau = (k as f64 - y.current_step as f64) * y.dt;
    if a.accel != 0.0 && (a.speed / a.accel) < 0.0 && tau > -a.speed / a.accel {
        let t_stop = -a.speed / a.accel;
        a.s + a.speed * t_stop + 0.5 * a.accel * t_stop * t_stop
    } else {
        a.s + a.speed * tau + 0.5 * a.accel * tau * tau
    }
}

/// Where a generated agent's states from the current step on leave its reference (the road,
/// or its route), which ends at `length`: the agent, the first step off it, which end, and how
/// far past it the agent gets. A car driven 120 m past a 50 m road's end loaded without a
/// word. Leaving may be meant, so this is said, not refused; a history that comes onto the
/// road is not said, as recorded agents enter a map's crop.
fn leaves_reference(a: &YamlAgent, y: &YamlScene, length: f64) -> Option<String> {
    // A static agent holds its pose at `valid_from` for the whole scene.
    let steps = if a.is_static {
        a.valid_from..a.valid_from + 1
    } else {
        a.valid_from.max(y.current_step)..y.steps
    };
    let mut first = None;
    let (mut before, mut past) = (0.0f64, 0.0f64);
    for k in steps {
        let s = s_at(a, y, k);
        if s < 0.0 || s > length {
            first.get_or_insert((k, s < 0.0));
            before = before.max(-s);
            past = past.max(s - length);
        }
    }
    let (k, starts_before) = first?;
    let m = |v: f64| crate::geom::num((v * 10.0).round() / 10.0);
    let how = match (before > 0.0, past > 0.0) {
        (true, true) => format!(
            "{} m before its start and {} m past its end",
            m(before),
            m(past)
        ),
        (true, false) => format!("up to {} m before its start", m(before)),
        _ => format!("up to {} m past its end", m(past)),
    };
    Some(format!(
        "{} (off {} from step {k}, {how})",
        a.id,
        if starts_before {
            "its start"
        } else {
            "its end"
        }
    ))
}

fn lane_motion(a: &YamlAgent, y: &YamlScene, reference: &FrenetPath, w: f64) -> Vec<AgentState> {
    let centre = |k: usize| (k as f64 + 0.5) * w;
    let pos = |k: usize| -> (f64, f64) {
        let tau = (k as f64 - y.current_step as f64) * y.dt;
        let s = s_at(a, y, k);
        let mut d = centre(a.lane) + a.d;
        if let Some(lc) = &a.lane_change {
            let u = ((tau - lc.start) / lc.duration.max(1e-6)).clamp(0.0, 1.0);
            d += (centre(lc.to) - centre(a.lane)) * 0.5 * (1.0 - (std::f64::consts::PI * u).cos());
        }
        (s, d)
    };
    let xy: Vec<Point> = (0..y.steps)
        .map(|k| {
            let (s, d) = pos(k);
            reference.to_cartesian(s, d)
        })
        .collect();
    let n = xy.len();
    (0..n)
        .map(|k| {
            let (lo, hi) = (k.saturating_sub(1), (k + 1).min(n - 1));
            let v = (xy[hi] - xy[lo]) / ((hi - lo).max(1) as f64 * y.dt);
            let heading = if v.norm() > 0.05 {
                let h = v.y.atan2(v.x);
                // Reversing keeps the body facing the road's direction.
                if a.speed < 0.0 {
                    crate::geom::wrap_angle(h + std::f64::consts::PI)
                } else {
                    h
                }
            } else {
                reference.heading_at(pos(k).0)
            };
            AgentState {
                x: xy[k].x,
                y: xy[k].y,
                heading,
                vx: v.x,
                vy: v.y,
                valid: true,
            }
        })
        .collect()
}

#[cfg(test)]
mod depth_tests {
    use super::{structure, Structure};

    fn too_deep(text: &str, max: usize) -> Option<usize> {
        match structure(text, max) {
            Some(Structure::TooDeep(line)) => Some(line),
            other => {
                assert_eq!(other, None);
                None
            }
        }
    }

    #[test]
    fn flow_nesting_is_measured_outside_quotes_and_comments() {
        assert_eq!(too_deep("a: [[1, 2], {b: [3]}]\n", 3), None);
        assert_eq!(too_deep("a: [[1, 2], {b: [[3]]}]\n", 3), Some(1));
        let text = "x: 1\ny: '[[[['\nz: \"{{{{\\\"\"\n# [[[[\nw: O'Brien\n";
        assert_eq!(too_deep(text, 2), None);
        // The apostrophe in a plain word opens no quote that would hide what follows.
        assert_eq!(too_deep(&format!("{text}v: [[[1]]]\n"), 2), Some(6));
        assert_eq!(too_deep("x: 1\ny: [\n [\n  [\n", 2), Some(4));
        let deep = format!("a: {}{}", "[".repeat(100_000), "]".repeat(100_000));
        assert_eq!(too_deep(&deep, 128), Some(1));
    }

    #[test]
    fn a_top_level_key_given_twice_and_a_second_document_are_found_by_line() {
        let st = |t: &str| structure(t, 128);
        assert_eq!(
            st("a: 1\nsteps: 60\nb: [1,\n  2]\nsteps: 61\n"),
            Some(Structure::DuplicateKey(5, "steps".into(), 2))
        );
        assert_eq!(
            st("scenes: x\r\nscenes: y\r\n"),
            Some(Structure::DuplicateKey(2, "scenes".into(), 1))
        );
        assert_eq!(
            st("# c\n---\na: 1\n---\nb: 2\n"),
            Some(Structure::SecondDocument(4))
        );
        // Not keys: nested ones (serde names those), text of block scalars, quoted
        // continuation lines, and a `---` that opens the one document.
        for text in [
            "a:\n  b: 1\n  b: 2\n",
            "a: |\n  a: 1\nb: 2\n",
            "a: \"x\nb: y\"\nb: 2\n",
            "---\na: 1\nb: 2\n",
            "a: 1 # a: 2\nb: 2\n",
            "s: |\n  ---\n  x\nt: 1\n",
            "agents:\n- {id: 1}\n- {id: 1}\n",
        ] {
            assert_eq!(st(text), None, "{text:?}");
        }
    }

    #[test]
    fn a_tag_is_found_where_a_value_starts_and_nowhere_else() {
        let tag = |t: &str| match structure(t, 128) {
            Some(Structure::Tag(line, tag)) => Some((line, tag)),
            _ => None,
        };
        assert_eq!(tag("a: 1\nid: !!str 1\n"), Some((2, "!!str".into())));
        assert_eq!(tag("- !point [1, 2]\n"), Some((1, "!point".into())));
        assert_eq!(tag("a: [1, !!int \"2\"]\n"), Some((1, "!!int".into())));
        assert_eq!(tag("!!map\na: 1\n"), Some((1, "!!map".into())));
        assert_eq!(tag("? !k a\n: 1\n"), Some((1, "!k".into())));
        // Past a block scalar's text, the lines are read again.
        assert_eq!(
            tag("a: |\n  !x\n\n  y\nb: !!str 1\n"),
            Some((5, "!!str".into()))
        );
        // Text, not tags: inside plain scalars, quotes and comments, and after a comma
        // outside flow collections (a plain scalar may hold `, !`).
        for text in [
            "a: wow!\n",
            "a: wow !nice\n",
            "a: 'x !y'\n",
            "a: \"!z\"\n",
            "a: 1 # !c\n",
            "a: x, !y\n",
            "a: some\n  !continued\n",
            "a: |\n  x: !not a tag\n\n  - !nor this\nb: 1\n",
            "- >\n    [[[[[\n",
        ] {
            assert_eq!(tag(text), None, "{text}");
        }
    }
}

#[cfg(test)]
mod alias_tests {
    use std::path::Path;

    /// A scene of 2000 crosswalks that are each one 2000-point polygon, 30 KB of text: over
    /// 12 million values once its aliases are expanded.
    fn bomb() -> String {
        let polygon: Vec<String> = (0..2000)
            .map(|i| format!("[{}, {}]", i % 7, i % 5))
            .collect();
        format!(
            "scenario_id: bomb\nsteps: 31\ncurrent_step: 10\nmap:\n  lanes:\n    - id: 1\n      \
             centerline: [[0, 0], [300, 0]]\n  crosswalks:\n    - &p [{}]\n{}agents:\n  - {{id: 1, \
             lane: 1, s: 10, speed: 10}}\n",
            polygon.join(", "),
            "    - *p\n".repeat(2000)
        )
    }

    #[test]
    fn aliases_expanding_past_the_budget_are_refused_before_filling_memory() {
        // The same scene of 460 KB took 3.4 GB and 14 s to read.
        let t0 = std::time::Instant::now();
        let e = super::parse(Path::new("bomb.yaml"), &bomb())
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("bomb.yaml: aliases: line ")
                && e.contains("its aliases (`*name`) expand it to more than 10000000 values"),
            "{e}"
        );
        assert!(t0.elapsed().as_secs() < 10, "{:?}", t0.elapsed());
        // A few aliases, as a hand-written scene may use them, are read as ever.
        let text = "scenario_id: reuse\nsteps: 31\ncurrent_step: 10\nmap:\n  lanes:\n    - id: 1\n      \
                    centerline: &c [[0, 0], [300, 0]]\n    - id: 2\n      centerline: [[0, 3.5], [300, 3.5]]\n  \
                    road_lines:\n    - {kind: broken, points: *c}\nagents:\n  - {id: 1, s: 10, speed: 10, \
                    route: [1]}\n";
        let reused = super::parse(Path::new("reuse.yaml"), text);
        assert!(reused.is_ok(), "{:?}", reused.err());
        assert_eq!(super::check_aliases(text), Ok(()));
        // A syntax error stays the reader's to report.
        assert_eq!(super::check_aliases("a: *nowhere\n"), Ok(()));
    }

    #[test]
    fn batch_and_script_test_files_have_the_same_alias_budget() {
        let dir = tempfile::tempdir().unwrap();
        let text = format!(
            "x: &p [{}]\ny:\n{}",
            vec!["[1, 2]"; 2000].join(", "),
            "  - *p\n".repeat(2000)
        );
        let batch = dir.path().join("batch.yaml");
        std::fs::write(&batch, &text).unwrap();
        let e = crate::llm::batch::read_batch(&batch)
            .unwrap_err()
            .to_string();
        assert!(e.contains("expand it to more than 10000000 values"), "{e}");
        let test = dir.path().join("x.test.yaml");
        std::fs::write(&test, &text).unwrap();
        let e = crate::cost::script_test::run_test_file(&test)
            .unwrap_err()
            .to_string();
        assert!(e.contains("expand it to more than 10000000 values"), "{e}");
        // And the same refusal of tags, naming the line; and of a top-level key given twice
        // and a second document, by line (serde named none).
        for (text, want) in [
            (
                "scenes: [a.yaml]\nentries:\n  - {scene: 0, request: !!str 1}\n",
                "line 3: YAML tags such as `!!str` are not read",
            ),
            (
                "scenes: [a.yaml]\nscenes: [b.yaml]\nentries: []\n",
                "line 2: `scenes` is given a second time (first on line 1)",
            ),
            (
                "scenes: [a.yaml]\nentries: []\n---\nscenes: [b.yaml]\n",
                "line 3: a second YAML document starts here (`---`)",
            ),
        ] {
            std::fs::write(&batch, text).unwrap();
            std::fs::write(&test, text).unwrap();
            for e in [
                crate::llm::batch::read_batch(&batch)
                    .unwrap_err()
                    .to_string(),
                crate::cost::script_test::run_test_file(&test)
                    .unwrap_err()
                    .to_string(),
            ] {
                assert!(e.contains(want), "{e}");
            }
        }
    }
}
