//! GPUDrive and Nocturne scenario JSON: one WOMD scenario per file, as GPUDrive's
//! `data_utils/process_waymo_files.py` and Nocturne's `waymo_scenario_construction.py` write it.
//!
//! The file is one JSON object: `objects` (one per WOMD track: `position` `[{x, y, z}]`,
//! `heading` `[rad]`, `velocity` `[{x, y}]`, `valid` `[bool]`, one entry per step; `width`,
//! `length`, `height`; `type`; `id`), `roads` (one per WOMD map feature: `geometry` `[{x, y,
//! z}]`, `type`, and in GPUDrive files `map_element_id` and `id`), `tl_states` (traffic-signal
//! states by lane) and, in GPUDrive files, `name`, `scenario_id` and `metadata`
//! (`sdc_track_index`, `objects_of_interest`, `tracks_to_predict`).
//!
//! Read as the WOMD proto reader ([`super::womd`]) reads the same scenario, with what the JSON
//! leaves out filled in by convention:
//! - **Time.** The JSON has no timestamps and no current index: steps are 0.1 s apart (WOMD's
//!   10 Hz, which both simulators step at) and the current step is 10, WOMD's
//!   `current_time_index` (1.1 s of history, 8 s of future in 91 steps), clamped to a shorter
//!   file's last step with a warning.
//! - **Headings.** GPUDrive writes radians, Nocturne degrees (its reader converts them). A file
//!   with `scenario_id` or `metadata` is GPUDrive's; one with neither is Nocturne's, and its
//!   objects may lack ids (they are then numbered by their place in `objects`, as Nocturne does;
//!   roads without ids likewise by their place in `roads`). The ego is GPUDrive's
//!   `metadata.sdc_track_index`, or the object Nocturne marks `is_av`.
//! - **Invalid states** carry the sentinel -10000 in the file; they are read as invalid states.
//! - **Lane connectivity is inferred.** The JSON keeps lane centre lines but drops WOMD's entry
//!   and exit lanes and neighbours. Lane `b` follows lane `a` when `a`'s last point lies within
//!   [`JOIN_GAP`] of `b`'s first and their directions there differ by at most [`JOIN_ANGLE`]
//!   degrees: WOMD's connected lanes share the end point exactly, tangent-continuous, so both
//!   bounds leave room and still refuse the near misses real files have (lanes ending 0.4-0.8
//!   m from another's start, running across or against it). No left/right neighbours are
//!   inferred: every lane is its road's only lane to scripts (`rightmost` holds everywhere).
//!   Intersection membership and speed limits are not in the file either (`false`, none).
//! - **Kinds** come from `map_element_id` (WOMD's type numbering, as Waymax uses it): lane type,
//!   road-line paint and road-edge kind. Without one (Nocturne), lanes are surface streets and
//!   lines and edges of unknown kind.
//! - **Not represented**, said in the scene's warnings as the WOMD reader says them:
//!   traffic-signal states, driveways, features with too few points. Stop signs are kept
//!   without the lanes they control (the JSON drops them). GPUDrive's `mark_as_expert` (agents
//!   its simulator replays from the log), `goalPosition`, heights, `objects_of_interest` and
//!   `tracks_to_predict` are not part of the scene model; WOMD marks no parked cars, so no agent
//!   is static.
//!
//! Errors name the file, the record (`objects[3] (id 1408)`, `roads[12] (id 40)`) and the field;
//! a JSON syntax or type error names the path to the value (`objects[3].position[40].x`).

use std::collections::{BTreeMap, HashMap, HashSet};
use std::path::Path;

use serde::de::{self, DeserializeSeed, IgnoredAny, MapAccess, Visitor};
use serde::Deserialize;

use super::IoError;
use crate::geom::{num, GeomError, Point, Polygon, Polyline, MAX_COORD};
use crate::scene::{
    Agent, AgentId, AgentState, AgentType, Lane, LaneType, Map, MapParts, RoadEdge, RoadEdgeKind,
    RoadLine, RoadLineKind, Scene, SceneError, SceneMeta, SourceFormat, StopLine,
};

/// Seconds between steps: WOMD's 10 Hz (the JSON stores no timestamps).
pub const DT: f64 = 0.1;
/// The current step: WOMD's `current_time_index` (the JSON stores none).
pub const CURRENT_STEP: usize = 10;
/// Steps of a WOMD scenario (1.1 s of history and 8 s of future at 10 Hz).
pub const WOMD_STEPS: usize = 91;
/// Largest gap, metres, between a lane's last point and the first point of a lane that follows
/// it.
pub const JOIN_GAP: f64 = 0.5;
/// Largest change of direction, degrees, from a lane's last segment to the first segment of a
/// lane that follows it.
pub const JOIN_ANGLE: f64 = 45.0;
/// Most lanes [`infer_lane_graph`] lets start at one lane's end (or end at one lane's start).
/// WOMD's busiest junctions give a lane a handful of successors; thousands of lanes stacked
/// on one spot, which a file of a few hundred KB can hold, made millions of links, minutes of
/// work and gigabytes of memory before anything was said.
pub const MAX_JOINS: usize = 32;

/// The object types the format writes (WOMD's track types), as agent types.
const OBJECT_TYPES: [(&str, AgentType); 5] = [
    ("vehicle", AgentType::Vehicle),
    ("pedestrian", AgentType::Pedestrian),
    ("cyclist", AgentType::Cyclist),
    ("other", AgentType::Other),
    ("unset", AgentType::Other),
];

/// The road types the format writes (WOMD's map feature kinds).
const ROAD_TYPES: [&str; 7] = [
    "lane",
    "road_line",
    "road_edge",
    "stop_sign",
    "crosswalk",
    "speed_bump",
    "driveway",
];

/// The `map_element_id` values each road type may carry (Waymax's numbering; -1 is unknown).
fn element_ids(kind: &str) -> std::ops::RangeInclusive<i64> {
    match kind {
        "lane" => 0..=3,
        "road_line" => 5..=13,
        "road_edge" => 14..=16,
        "stop_sign" => 17..=17,
        "crosswalk" => 18..=18,
        "speed_bump" => 19..=19,
        _ => 20..=20,
    }
}

/// Traffic-signal states as the converters write them (WOMD's lane states).
const SIGNAL_STATES: [&str; 9] = [
    "unknown",
    "arrow_stop",
    "arrow_caution",
    "arrow_go",
    "stop",
    "caution",
    "go",
    "flashing_stop",
    "flashing_caution",
];

#[derive(Deserialize)]
struct Xy {
    x: f64,
    y: f64,
}

impl Xy {
    fn point(&self) -> Point {
        Point::new(self.x, self.y)
    }
}

#[derive(Deserialize)]
struct Object {
    position: Vec<Xy>,
    heading: Vec<f64>,
    velocity: Vec<Xy>,
    valid: Vec<bool>,
    width: f64,
    length: f64,
    #[serde(rename = "type")]
    kind: String,
    #[serde(default)]
    id: Option<i64>,
    /// Nocturne's mark of the self-driving car (GPUDrive gives `metadata.sdc_track_index`).
    #[serde(default)]
    is_av: Option<bool>,
}

#[derive(Deserialize)]
struct Road {
    geometry: Vec<Xy>,
    #[serde(rename = "type")]
    kind: String,
    #[serde(default)]
    map_element_id: Option<i64>,
    #[serde(default)]
    id: Option<i64>,
}

#[derive(Deserialize)]
struct Signal {
    state: Vec<String>,
    x: Vec<f64>,
    y: Vec<f64>,
    time_index: Vec<i64>,
}

#[derive(Deserialize)]
struct Metadata {
    #[serde(default)]
    sdc_track_index: Option<i64>,
}

#[derive(Deserialize)]
struct File {
    #[serde(default)]
    scenario_id: Option<String>,
    objects: Vec<Object>,
    roads: Vec<Road>,
    #[serde(default)]
    tl_states: Option<BTreeMap<String, Signal>>,
    #[serde(default)]
    metadata: Option<Metadata>,
}

/// Whether `path` holds a GPUDrive/Nocturne scenario: a JSON object with a top-level `objects`
/// or `roads` key (no other JSON that drivescript reads or writes has either). Only the keys
/// before the first of them are read. A damaged scenario still counts once either key has been
/// seen, so that the reader can say what is wrong with it; a file that cannot be opened does
/// not.
pub fn is_scenario_file(path: &Path) -> bool {
    use std::io::Read;
    // No size cap here: a scenario too large to read is the reader's to refuse, saying so.
    let Ok(file) = super::open_regular(path, u64::MAX, "a scene file") else {
        return false;
    };
    let reader = std::io::BufReader::new(file.take(super::MAX_SCENE_BYTES));
    let mut found = false;
    let mut de = serde_json::Deserializer::from_reader(reader);
    // Stops with an error at the first key it wants: `found` says why it stopped.
    let _ = TopKeys(&mut found).deserialize(&mut de);
    found
}

struct TopKeys<'a>(&'a mut bool);

impl<'de> DeserializeSeed<'de> for TopKeys<'_> {
    type Value = ();
    fn deserialize<D: de::Deserializer<'de>>(self, d: D) -> Result<(), D::Error> {
        d.deserialize_map(self)
    }
}

impl<'de> Visitor<'de> for TopKeys<'_> {
    type Value = ();
    fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
        f.write_str("a JSON object")
    }
    fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<(), A::Error> {
        while let Some(key) = map.next_key::<String>()? {
            if key == "objects" || key == "roads" {
                *self.0 = true;
                return Err(de::Error::custom("found"));
            }
            map.next_value::<IgnoredAny>()?;
        }
        Ok(())
    }
}

/// Reads a GPUDrive or Nocturne scenario file (see the module documentation).
pub fn read(path: &Path) -> Result<Scene, IoError> {
    let text = super::read_text(path)?;
    parse(path, &text)
}

/// Parses the text of a scenario file read from `path` (named in errors).
pub fn parse(path: &Path, text: &str) -> Result<Scene, IoError> {
    let file: File = serde_json::from_str(text).map_err(|e| json_error(path, text, &e))?;
    to_scene(path, file)
}

/// A serde error as the path to the value it is about (`objects[3].position[40].x`), the line
/// and column, and the reason; with a word on the two ways real files go wrong that serde's
/// message does not name (a file cut short, Python's non-JSON `NaN`). Rollout files are read
/// through it too.
pub(crate) fn json_error(path: &Path, text: &str, e: &serde_json::Error) -> IoError {
    let offset = byte_offset(text, e.line(), e.column());
    let at = json_path(text, offset);
    let mut message = super::without_position(&e.to_string(), e.line(), e.column());
    if e.is_eof() {
        message.push_str(" (the file ends early: it is cut short)");
    }
    let around = &text.as_bytes()[offset.saturating_sub(2)..(offset + 9).min(text.len())];
    let around = String::from_utf8_lossy(around);
    if e.is_syntax() && (around.contains("NaN") || around.contains("Infinity")) {
        message.push_str(
            " (NaN and Infinity are not JSON: Python's json.dump writes them for a value that \
             is not a number, which no scene can use)",
        );
    }
    let place = format!("line {}, column {}", e.line(), e.column());
    IoError::invalid(
        path,
        if at.is_empty() {
            place
        } else {
            format!("{at} ({place})")
        },
        message,
    )
}

/// The byte offset of serde_json's `line` (from 1) and `column` (bytes before the position on
/// that line), clamped to the text.
fn byte_offset(text: &str, line: usize, column: usize) -> usize {
    let start = if line <= 1 {
        0
    } else {
        text.match_indices('\n')
            .nth(line - 2)
            .map_or(text.len(), |(i, _)| i + 1)
    };
    (start + column).min(text.len())
}

/// The path to the JSON value being read at byte `offset` of `text`: keys and array indices
/// from the top (`objects[3].position[40].x`), empty at the top level. A scan that tracks only
/// nesting, keys and commas: the text before the offset is what the parser accepted.
fn json_path(text: &str, offset: usize) -> String {
    enum Frame {
        Object { key: Option<String>, in_key: bool },
        Array(usize),
    }
    let mut stack: Vec<Frame> = Vec::new();
    let bytes = &text.as_bytes()[..offset];
    let mut i = 0;
    while i < bytes.len() {
        match bytes[i] {
            b'"' => {
                let start = i + 1;
                i += 1;
                while i < bytes.len() && bytes[i] != b'"' {
                    i += if bytes[i] == b'\\' { 2 } else { 1 };
                }
                if let Some(Frame::Object { key, in_key: true }) = stack.last_mut() {
                    let end = i.min(bytes.len());
                    *key = Some(String::from_utf8_lossy(&bytes[start..end]).into_owned());
                }
            }
            b'{' => stack.push(Frame::Object {
                key: None,
                in_key: true,
            }),
            b'[' => stack.push(Frame::Array(0)),
            b'}' | b']' => {
                stack.pop();
            }
            b':' => {
                if let Some(Frame::Object { in_key, .. }) = stack.last_mut() {
                    *in_key = false;
                }
            }
            b',' => match stack.last_mut() {
                Some(Frame::Array(n)) => *n += 1,
                Some(Frame::Object { key, in_key }) => {
                    *key = None;
                    *in_key = true;
                }
                None => {}
            },
            _ => {}
        }
        i += 1;
    }
    let mut out = String::new();
    for f in &stack {
        match f {
            Frame::Object { key: Some(k), .. } => {
                if !out.is_empty() {
                    out.push('.');
                }
                out.push_str(k);
            }
            Frame::Object { key: None, .. } => {}
            Frame::Array(n) => out.push_str(&format!("[{n}]")),
        }
    }
    out
}

/// `objects[i] (id X)` or `objects[i]`.
fn object_at(i: usize, id: Option<i64>) -> String {
    match id {
        Some(id) => format!("objects[{i}] (id {id})"),
        None => format!("objects[{i}]"),
    }
}

/// `roads[k] (id X)` or `roads[k]`.
fn road_at(k: usize, id: Option<i64>) -> String {
    match id {
        Some(id) => format!("roads[{k}] (id {id})"),
        None => format!("roads[{k}]"),
    }
}

fn to_scene(path: &Path, file: File) -> Result<Scene, IoError> {
    let bad = |at: String, msg: String| IoError::invalid(path, at, msg);
    // GPUDrive writes both; Nocturne neither, and gives headings in degrees.
    let gpudrive = file.scenario_id.is_some() || file.metadata.is_some();
    let mut warnings = Vec::new();

    let Some(first) = file.objects.first() else {
        return Err(bad(
            "objects".into(),
            "is empty: a scenario has at least one object (WOMD's self-driving car), and the \
             objects are what gives the scene its steps"
                .into(),
        ));
    };
    let steps = first.position.len();
    if steps == 0 {
        return Err(bad(
            format!("{}.position", object_at(0, first.id)),
            "is empty: an object has one state per step".into(),
        ));
    }
    if steps > super::MAX_STEPS {
        return Err(bad(
            format!("{}.position", object_at(0, first.id)),
            format!(
                "{steps} steps is implausible (limit {}; WOMD has {WOMD_STEPS})",
                super::MAX_STEPS
            ),
        ));
    }
    super::check_states(path, "objects", file.objects.len(), steps)?;

    let mut agents = Vec::with_capacity(file.objects.len());
    let mut seen: HashMap<AgentId, usize> = HashMap::new();
    for (i, o) in file.objects.iter().enumerate() {
        let at = object_at(i, o.id);
        for (field, n) in [
            ("position", o.position.len()),
            ("heading", o.heading.len()),
            ("velocity", o.velocity.len()),
            ("valid", o.valid.len()),
        ] {
            if n != steps {
                return Err(bad(
                    format!("{at}.{field}"),
                    format!(
                        "has {n} entries, but the scene has {steps} steps (objects[0].position \
                         has {steps}): every object has one position, heading, velocity and \
                         valid flag per step"
                    ),
                ));
            }
        }
        let agent_type = OBJECT_TYPES
            .iter()
            .find(|(name, _)| *name == o.kind)
            .map(|(_, t)| *t)
            .ok_or_else(|| {
                bad(
                    format!("{at}.type"),
                    format!(
                        "{:?} is not an object type of the format ({})",
                        o.kind,
                        OBJECT_TYPES.map(|(n, _)| n).join(", ")
                    ),
                )
            })?;
        let id =
            match o.id {
                Some(id) => id,
                None if !gpudrive => i as i64,
                None => return Err(bad(
                    format!("{at}.id"),
                    "is missing: a GPUDrive file (one with scenario_id or metadata) gives every \
                     object its WOMD track id"
                        .into(),
                )),
            };
        if let Some(j) = seen.insert(id, i) {
            return Err(bad(
                format!("{at}.id"),
                format!("{id} is also the id of objects[{j}]: track ids are unique"),
            ));
        }
        let mut states = Vec::with_capacity(steps);
        for t in 0..steps {
            if !o.valid[t] {
                states.push(AgentState::INVALID);
                continue;
            }
            let h = o.heading[t];
            let heading = if gpudrive {
                // GPUDrive wraps headings into [-pi, pi]: a larger one is most likely degrees
                // (a Nocturne file given GPUDrive's keys), which would spin the agent.
                if h.abs() > std::f64::consts::TAU {
                    return Err(bad(
                        format!("{at}.heading[{t}]"),
                        format!(
                            "{} is not an angle in radians as GPUDrive writes them (-pi to pi); \
                             Nocturne files give degrees, and have no scenario_id or metadata",
                            num(h)
                        ),
                    ));
                }
                h
            } else {
                h.to_radians()
            };
            states.push(AgentState {
                x: o.position[t].x,
                y: o.position[t].y,
                heading,
                vx: o.velocity[t].x,
                vy: o.velocity[t].y,
                valid: true,
            });
        }
        agents.push(Agent {
            id,
            agent_type,
            length: o.length,
            width: o.width,
            states,
            is_static: false,
        });
    }
    let ids: Vec<AgentId> = agents.iter().map(|a| a.id).collect();
    // An object never observed has nothing to replay or to start a sample from: a file of
    // such objects loaded as a scene of agents that are nowhere, ego included, without a word.
    let unseen: Vec<String> = agents
        .iter()
        .filter(|a| a.states.iter().all(|s| !s.valid))
        .map(|a| a.id.to_string())
        .collect();
    if !agents.is_empty() && unseen.len() == agents.len() {
        return Err(bad(
            "objects".into(),
            format!(
                "no object is observed at any step ({} objects, every `valid` false): the file \
                 holds no traffic",
                agents.len()
            ),
        ));
    }
    if !unseen.is_empty() {
        warnings.push(format!(
            "object{} {} never observed (every `valid` false): kept as agents with no state",
            if unseen.len() == 1 { "" } else { "s" },
            super::first_few(&unseen)
        ));
    }

    let sdc = file.metadata.as_ref().and_then(|m| m.sdc_track_index);
    let marked: Vec<usize> = (file.objects.iter().enumerate())
        .filter(|(_, o)| o.is_av == Some(true))
        .map(|(i, _)| i)
        .collect();
    // The first of two was taken for the ego without a word.
    if let [first, second, ..] = marked[..] {
        return Err(bad(
            format!("objects[{second}].is_av"),
            format!("objects[{first}] is marked is_av too: a scenario has one self-driving car"),
        ));
    }
    let av = marked.first().map(|&i| i as i64);
    let ego = match sdc.or(av) {
        Some(k) => Some(
            usize::try_from(k)
                .ok()
                .and_then(|k| ids.get(k).copied())
                .ok_or_else(|| {
                    bad(
                        "metadata.sdc_track_index".into(),
                        format!("{k} is not an index into objects (0 to {})", ids.len() - 1),
                    )
                })?,
        ),
        None => None,
    };

    let current_step = CURRENT_STEP.min(steps - 1);
    if steps != WOMD_STEPS {
        warnings.push(format!(
            "{steps} steps, not WOMD's {WOMD_STEPS}: the file does not say where history ends, \
             so step {current_step} is the current step (WOMD's is 10)"
        ));
    }

    let parts = read_roads(path, &file.roads, &mut warnings)?;
    let signals = read_signals(path, file.tl_states.as_ref(), steps)?;
    if signals > 0 {
        warnings.push(format!(
            "{signals} traffic-signal lane states not represented in the scene model"
        ));
    }
    let map = Map::new(parts).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        location: "roads".into(),
        error: e,
    })?;
    let scenario_id = match file.scenario_id {
        Some(id) if !id.is_empty() => id,
        _ => super::file_stem(path),
    };
    let meta = SceneMeta {
        source_format: SourceFormat::Gpudrive,
        source_file: path.display().to_string(),
        scenario_id,
        dt: DT,
        current_step,
        ego,
        warnings,
    };
    Scene::recorded(meta, map, agents).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        location: agent_of(&e)
            .and_then(|a| {
                ids.iter()
                    .position(|x| *x == a)
                    .map(|i| object_at(i, Some(a)))
            })
            .unwrap_or_else(|| match e {
                SceneError::ScenarioId { .. } | SceneError::ScenarioIdTooLong { .. } => {
                    "scenario_id".into()
                }
                _ => "objects".into(),
            }),
        error: e,
    })
}

/// The agent a scene error is about, if one.
fn agent_of(e: &SceneError) -> Option<AgentId> {
    match e {
        SceneError::DuplicateAgent(a)
        | SceneError::StepCount { agent: a, .. }
        | SceneError::NonFiniteState { agent: a, .. }
        | SceneError::BadSize { agent: a, .. }
        | SceneError::Implausible { agent: a, .. } => Some(*a),
        _ => None,
    }
}

/// The map features, and the lane graph inferred from lane end points.
fn read_roads(
    path: &Path,
    roads: &[Road],
    warnings: &mut Vec<String>,
) -> Result<MapParts, IoError> {
    let bad = |at: String, msg: String| IoError::invalid(path, at, msg);
    let mut parts = MapParts::default();
    let mut driveways = 0;
    let mut lane_ids: HashMap<i64, usize> = HashMap::new();
    for (k, r) in roads.iter().enumerate() {
        let at = road_at(k, r.id);
        if !ROAD_TYPES.contains(&r.kind.as_str()) {
            return Err(bad(
                format!("{at}.type"),
                format!(
                    "{:?} is not a road type of the format ({})",
                    r.kind,
                    ROAD_TYPES.join(", ")
                ),
            ));
        }
        let element = match r.map_element_id {
            Some(-1) | None => None,
            Some(e) if element_ids(&r.kind).contains(&e) => Some(e),
            Some(e) => {
                let range = element_ids(&r.kind);
                return Err(bad(
                    format!("{at}.map_element_id"),
                    format!(
                        "{e} is not a {}'s (WOMD's numbering gives it {}{}, or -1 for unknown)",
                        r.kind,
                        range.start(),
                        if range.start() == range.end() {
                            String::new()
                        } else {
                            format!(" to {}", range.end())
                        }
                    ),
                ));
            }
        };
        // Nocturne writes no road ids (and GPUDrive's own reader does not need them): the
        // place in `roads` stands in, and a clash with a given lane id is refused below.
        let fid = r.id.unwrap_or(k as i64);
        let points = || r.geometry.iter().map(Xy::point);
        // A line with fewer than two distinct points is skipped with a word, as the WOMD
        // reader does; a point that is no coordinate at all is an error.
        let line = || -> Result<Option<Polyline>, IoError> {
            match Polyline::new(points()) {
                Ok(l) => Ok(Some(l)),
                Err(GeomError::TooFewPoints { .. }) => Ok(None),
                Err(e) => Err(bad(format!("{at}.geometry"), e.to_string())),
            }
        };
        let polygon = || -> Result<Option<Polygon>, IoError> {
            match Polygon::new(points()) {
                Ok(p) => Ok(Some(p)),
                Err(GeomError::TooFewPoints { .. }) => Ok(None),
                Err(e) => Err(bad(format!("{at}.geometry"), e.to_string())),
            }
        };
        match r.kind.as_str() {
            "lane" => {
                let Some(center) = line()? else {
                    warnings.push(format!(
                        "lane {fid} skipped: its polyline has fewer than 2 distinct points"
                    ));
                    continue;
                };
                if let Some(j) = lane_ids.insert(fid, k) {
                    return Err(bad(
                        format!("{at}.id"),
                        format!("{fid} is also the id of the lane roads[{j}]: lane ids are unique"),
                    ));
                }
                let mut lane = Lane::new(fid, center);
                // As the WOMD reader: undefined (0) or unknown (-1) is `Other`. Nocturne
                // writes no kinds, and its lanes are the roads' lanes.
                lane.lane_type = match r.map_element_id {
                    None | Some(2) => LaneType::SurfaceStreet,
                    Some(1) => LaneType::Freeway,
                    Some(3) => LaneType::Bike,
                    _ => LaneType::Other,
                };
                parts.lanes.push(lane);
            }
            "road_edge" => {
                let Some(l) = line()? else {
                    warnings.push(format!(
                        "road edge {fid} skipped: fewer than 2 distinct points"
                    ));
                    continue;
                };
                let kind = match element {
                    Some(15) => RoadEdgeKind::Boundary,
                    Some(16) => RoadEdgeKind::Median,
                    _ => RoadEdgeKind::Unknown,
                };
                parts.road_edges.push(RoadEdge::new(kind, l));
            }
            "road_line" => {
                let Some(l) = line()? else {
                    warnings.push(format!(
                        "road line {fid} skipped: fewer than 2 distinct points"
                    ));
                    continue;
                };
                let kind = match element {
                    Some(6 | 9 | 10) => RoadLineKind::Broken,
                    Some(7 | 11) => RoadLineKind::Solid,
                    Some(8 | 12 | 13) => RoadLineKind::DoubleSolid,
                    _ => RoadLineKind::Unknown,
                };
                parts.road_lines.push(RoadLine {
                    kind,
                    yellow: element.is_some_and(|e| (9..=13).contains(&e)),
                    line: l,
                });
            }
            "stop_sign" => {
                let Some(p) = r.geometry.first().map(Xy::point) else {
                    warnings.push(format!("stop sign {fid} skipped: no position"));
                    continue;
                };
                if !(p.x.is_finite() && p.y.is_finite())
                    || p.x.abs() > MAX_COORD
                    || p.y.abs() > MAX_COORD
                {
                    return Err(bad(
                        format!("{at}.geometry[0]"),
                        format!(
                            "({}, {}) is not a map coordinate (at most {MAX_COORD:e} m from the \
                             origin)",
                            num(p.x),
                            num(p.y)
                        ),
                    ));
                }
                parts.stop_lines.push(StopLine {
                    points: vec![p],
                    lanes: Vec::new(),
                });
            }
            "crosswalk" | "speed_bump" => {
                let what = if r.kind == "crosswalk" {
                    "crosswalk"
                } else {
                    "speed bump"
                };
                match polygon()? {
                    Some(p) if r.kind == "crosswalk" => parts.crosswalks.push(p),
                    Some(p) => parts.speed_bumps.push(p),
                    None => warnings.push(format!(
                        "{what} {fid} skipped: fewer than 3 distinct points"
                    )),
                }
            }
            _ => driveways += 1,
        }
    }
    if driveways > 0 {
        warnings.push(format!(
            "{driveways} driveways not represented in the scene model"
        ));
    }
    // A lane drawn out and back loaded without a word, its 40 m read as 120 m.
    warnings.extend(super::turning_back_warning(&parts.lanes));
    if let Err(crowd) = infer_lane_graph(&mut parts.lanes) {
        let k = lane_ids.get(&crowd.lane).copied().unwrap_or_default();
        let (them, here) = if crowd.at_end {
            ("start", "end")
        } else {
            ("end", "start")
        };
        return Err(bad(
            road_at(k, Some(crowd.lane)),
            format!(
                "more than {MAX_JOINS} lanes {them} within {JOIN_GAP} m of its {here}, in its \
                 direction; no junction joins so many: the file stacks lanes on one spot, \
                 which is no road network"
            ),
        ));
    }
    Ok(parts)
}

/// Links each lane to the lanes that start where it ends: `b` follows `a` when `a`'s last
/// point lies within [`JOIN_GAP`] of `b`'s first and the direction turns by at most
/// [`JOIN_ANGLE`] from `a`'s last segment to `b`'s first (see the module documentation for
/// why these bounds). Existing edges are kept. A lane that more than [`MAX_JOINS`] lanes
/// would follow, or precede, is an error, and no lane is linked.
pub fn infer_lane_graph(lanes: &mut [Lane]) -> Result<(), CrowdedJoin> {
    let min_cos = JOIN_ANGLE.to_radians().cos();
    let ends: Vec<(Point, Point, Point, Point)> = lanes
        .iter()
        .map(|l| {
            let c = &l.centerline;
            (
                c.first(),
                c.segment_direction(0),
                c.last(),
                c.segment_direction(c.segment_count() - 1),
            )
        })
        .collect();
    let ids: Vec<i64> = lanes.iter().map(|l| l.id).collect();
    // Starts bucketed in cells of JOIN_GAP, so that each end is compared with the starts of
    // the 3 x 3 cells around it only: comparing every end with every start took minutes for
    // a file of a few thousand lanes.
    // Each end is compared with the starts near it only: comparing every end with every start
    // took minutes for a file of a few thousand lanes.
    let mut starts = crate::geom::CellIndex::new(JOIN_GAP, 1);
    for (b, &(start, ..)) in ends.iter().enumerate() {
        starts.insert(b, start, start);
    }
    // Counted as they are found, so that a crowded spot is refused before its links fill
    // memory.
    let mut outs = vec![0usize; lanes.len()];
    let mut ins = vec![0usize; lanes.len()];
    let mut links = Vec::new();
    for (a, &(_, _, end, end_dir)) in ends.iter().enumerate() {
        for b in starts.around(end) {
            let (start, start_dir, _, _) = ends[b];
            if a != b && (start - end).norm() <= JOIN_GAP && end_dir.dot(&start_dir) >= min_cos {
                links.push((a, b));
                outs[a] += 1;
                ins[b] += 1;
                for (lane, count, at_end) in [(a, outs[a], true), (b, ins[b], false)] {
                    if count > MAX_JOINS {
                        return Err(CrowdedJoin {
                            lane: ids[lane],
                            count,
                            at_end,
                        });
                    }
                }
            }
        }
    }
    // Sets beside the lists: `contains` on a list per link made a lane that thousands of
    // lanes start at cost the cube of their number.
    let mut succ: Vec<HashSet<i64>> = lanes
        .iter()
        .map(|l| l.successors.iter().copied().collect())
        .collect();
    let mut pred: Vec<HashSet<i64>> = lanes
        .iter()
        .map(|l| l.predecessors.iter().copied().collect())
        .collect();
    links.sort_unstable();
    for (a, b) in links {
        if succ[a].insert(ids[b]) {
            lanes[a].successors.push(ids[b]);
        }
        if pred[b].insert(ids[a]) {
            lanes[b].predecessors.push(ids[a]);
        }
    }
    Ok(())
}

/// A lane [`infer_lane_graph`] would join to more than [`MAX_JOINS`] lanes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct CrowdedJoin {
    /// The lane.
    pub lane: i64,
    /// How many lanes had been found to follow it (or precede it) when the search stopped:
    /// one more than [`MAX_JOINS`].
    pub count: usize,
    /// Whether they start at its end (else they end at its start).
    pub at_end: bool,
}

/// Checks the traffic-signal states (per lane: a state, a stop point and a step for each
/// entry) and counts them: the scene model has no signals, so they are reported, not kept.
fn read_signals(
    path: &Path,
    signals: Option<&BTreeMap<String, Signal>>,
    steps: usize,
) -> Result<usize, IoError> {
    let mut count = 0;
    for (lane, s) in signals.into_iter().flatten() {
        let at = format!("tl_states.{lane}");
        let bad = |field: &str, msg: String| IoError::invalid(path, format!("{at}.{field}"), msg);
        if lane.parse::<i64>().is_err() {
            return Err(IoError::invalid(
                path,
                &at,
                "is not a lane id: the converters key signal states by the lane they control",
            ));
        }
        let n = s.state.len();
        for (field, len) in [
            ("x", s.x.len()),
            ("y", s.y.len()),
            ("time_index", s.time_index.len()),
        ] {
            if len != n {
                return Err(bad(
                    field,
                    format!("has {len} entries, state has {n}: one per recorded state"),
                ));
            }
        }
        if let Some((j, st)) = s
            .state
            .iter()
            .enumerate()
            .find(|(_, st)| !SIGNAL_STATES.contains(&st.as_str()))
        {
            return Err(bad(
                &format!("state[{j}]"),
                format!(
                    "{st:?} is not a signal state of the format ({})",
                    SIGNAL_STATES.join(", ")
                ),
            ));
        }
        if let Some((j, t)) = s
            .time_index
            .iter()
            .enumerate()
            .find(|(_, t)| usize::try_from(**t).map_or(true, |t| t >= steps))
        {
            return Err(bad(
                &format!("time_index[{j}]"),
                format!("{t} is not one of the scene's {steps} steps"),
            ));
        }
        count += n;
    }
    Ok(count)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn fixture() -> std::path::PathBuf {
        Path::new(env!("CARGO_MANIFEST_DIR")).join("tests/data/gpudrive/synthetic_junction.json")
    }

    fn scene() -> Scene {
        read(&fixture()).unwrap()
    }

    #[test]
    fn the_synthetic_junction_reads_with_known_agents_and_steps() {
        let s = scene();
        assert_eq!(s.meta.source_format, SourceFormat::Gpudrive);
        assert_eq!(s.meta.scenario_id, "synthetic_junction");
        assert_eq!(
            (s.num_steps(), s.meta.current_step, s.meta.dt),
            (91, 10, 0.1)
        );
        let kinds: Vec<(i64, AgentType)> = s.agents.iter().map(|a| (a.id, a.agent_type)).collect();
        assert_eq!(
            kinds,
            vec![
                (101, AgentType::Vehicle),
                (202, AgentType::Cyclist),
                (303, AgentType::Pedestrian),
                (404, AgentType::Vehicle),
            ]
        );
        assert_eq!(s.meta.ego, Some(101));
        // The pedestrian appears at step 5; the others are seen throughout.
        let span = |id| s.agent(id).unwrap().valid_span();
        assert_eq!(span(303), Some((5, 90)));
        assert_eq!(s.agent(303).unwrap().valid_count(), 86);
        assert!(!s.agent(303).unwrap().is_valid(4));
        for id in [101, 202, 404] {
            assert_eq!(span(id), Some((0, 90)));
        }
        // The parked car stands still and, as in WOMD, is not marked static.
        let parked = s.agent(404).unwrap();
        assert!(parked.states.iter().all(|st| st.speed() == 0.0));
        assert!(!parked.is_static);
        // Radians as written, velocities and sizes as written.
        let car = s.agent(101).unwrap();
        let c = car.states[10];
        assert!((c.x - (-45.0 + 8.0)).abs() < 1e-9 && (c.y + 1.75).abs() < 1e-9);
        assert!((c.vx - 8.0).abs() < 1e-9 && c.heading == 0.0);
        assert_eq!((car.length, car.width), (4.5, 2.0));
        let bike = s.agent(202).unwrap();
        assert!((bike.states[0].heading - std::f64::consts::PI).abs() < 1e-9);
    }

    #[test]
    fn the_synthetic_junction_map_and_its_inferred_lane_graph() {
        let s = scene();
        let m = &s.map;
        assert_eq!(m.lanes().len(), 11);
        assert_eq!(
            (m.road_edges().len(), m.road_lines().len()),
            (4, 2),
            "edges and the centre line"
        );
        assert_eq!(
            (
                m.crosswalks().len(),
                m.speed_bumps().len(),
                m.stop_lines().len()
            ),
            (1, 1, 1)
        );
        assert_eq!(m.road_lines()[0].kind, RoadLineKind::DoubleSolid);
        assert!(m.road_lines()[0].yellow);
        assert_eq!(m.road_edges()[0].kind, RoadEdgeKind::Boundary);
        assert_eq!(m.lane(3).unwrap().lane_type, LaneType::SurfaceStreet);
        let g = m.graph();
        let sorted = |v: &[i64]| {
            let mut v = v.to_vec();
            v.sort();
            v
        };
        // Eastbound approach 1: straight on (2), right (4) or left (6); westbound approach 8:
        // straight on (9) or right (11). The exits end at the map's edge.
        assert_eq!(sorted(g.successors(1)), vec![2, 4, 6]);
        assert_eq!(g.successors(2), &[3]);
        assert_eq!(g.successors(4), &[5]);
        assert_eq!(g.successors(6), &[7]);
        assert_eq!(sorted(g.successors(8)), vec![9, 11]);
        assert_eq!(g.successors(9), &[10]);
        assert_eq!(g.successors(11), &[7]);
        for exit in [3, 5, 7, 10] {
            assert!(g.successors(exit).is_empty(), "lane {exit}");
        }
        assert_eq!(sorted(g.predecessors(7)), vec![6, 11]);
        assert_eq!(g.predecessors(1), &[] as &[i64]);
        let with_successors = m
            .lanes()
            .iter()
            .filter(|l| !g.successors(l.id).is_empty())
            .count();
        assert_eq!(with_successors, 7);
        assert_eq!(g.dangling(), 0);
        let w = s.meta.warnings.join("\n");
        assert!(w.contains("1 driveways not represented"), "{w}");
        assert!(
            w.contains("3 traffic-signal lane states not represented"),
            "{w}"
        );
        assert_eq!(s.meta.warnings.len(), 2, "{w}");
    }

    #[test]
    fn lanes_join_only_end_to_start_close_and_in_line() {
        let lane = |id, pts: &[(f64, f64)]| {
            Lane::new(
                id,
                Polyline::new(pts.iter().map(|&(x, y)| Point::new(x, y))).unwrap(),
            )
        };
        let mut lanes = vec![
            lane(1, &[(0.0, 0.0), (10.0, 0.0)]),
            // 0.4 m on, in line: follows 1.
            lane(2, &[(10.4, 0.0), (20.0, 0.0)]),
            // 0.3 m from 1's end, but across it.
            lane(3, &[(10.0, 0.3), (10.0, 10.0)]),
            // In line, but 0.8 m on.
            lane(4, &[(10.8, 0.1), (20.0, 0.1)]),
            // Starts where 1 ends, turning 40 degrees: a turn lane.
            lane(5, &[(10.0, 0.0), (17.66, 6.43)]),
            // Ends where 1 starts but runs against it.
            lane(6, &[(5.0, 0.0), (0.0, 0.0)]),
        ];
        infer_lane_graph(&mut lanes).unwrap();
        assert_eq!(lanes[0].successors, vec![2, 5]);
        assert_eq!(lanes[1].predecessors, vec![1]);
        assert!(lanes[2].predecessors.is_empty() && lanes[3].predecessors.is_empty());
        assert!(lanes[5].successors.is_empty(), "{:?}", lanes[5].successors);
    }

    #[test]
    fn nocturne_files_give_degrees_and_no_ids() {
        // As GPUDrive's own test files (tests/agent-agent-collision.json) are written.
        let text = r#"{"name": "n.json", "objects": [
            {"position": [{"x": 0, "y": 0}, {"x": 0, "y": 1}], "width": 1, "length": 2,
             "heading": [90, 90], "velocity": [{"x": 0, "y": 10}, {"x": 0, "y": 10}],
             "valid": [true, true], "goalPosition": {"x": 0, "y": 1}, "type": "vehicle"},
            {"position": [{"x": 5, "y": 5}, {"x": -10000, "y": -10000}], "width": 1,
             "length": 1, "heading": [0, -10000], "velocity": [{"x": 0, "y": 0},
             {"x": -10000, "y": -10000}], "valid": [true, false], "type": "unset", "is_av": true}],
          "roads": [{"geometry": [{"x": 0, "y": -5}, {"x": 0, "y": 20}], "type": "lane"},
                    {"geometry": [{"x": 3, "y": -5}, {"x": 3, "y": 20}], "type": "road_edge"}],
          "tl_states": {}}"#;
        let s = parse(Path::new("dir/n.json"), text).unwrap();
        assert_eq!(s.meta.scenario_id, "n");
        assert_eq!(
            s.agents.iter().map(|a| a.id).collect::<Vec<_>>(),
            vec![0, 1]
        );
        assert!((s.agents[0].states[0].heading - std::f64::consts::FRAC_PI_2).abs() < 1e-12);
        assert_eq!(s.agents[1].agent_type, AgentType::Other);
        assert_eq!(s.meta.ego, Some(1), "the object marked is_av");
        assert!(!s.agents[1].is_valid(1));
        assert_eq!(s.meta.current_step, 1, "10 clamped to the last step");
        assert!(s.meta.warnings[0].contains("2 steps, not WOMD's 91"));
        assert_eq!(s.map.lanes()[0].id, 0);
        assert_eq!(s.map.road_edges()[0].kind, RoadEdgeKind::Unknown);
    }

    #[test]
    fn json_errors_name_the_path_to_the_value() {
        let p = Path::new("x.json");
        let e = |text: &str| parse(p, text).unwrap_err().to_string();
        let err = e(r#"{"objects": [{"position": [{"x": 1, "y": 2}, {"x": "a", "y": 2}]}]}"#);
        assert!(
            err.starts_with("x.json: objects[0].position[1].x (line 1, column"),
            "{err}"
        );
        assert!(
            err.contains("invalid type: string \"a\", expected a number"),
            "{err}"
        );
        let err = e("{\"objects\": [{\"position\": [{\"x\": 1,\n \"y\": 2}, {\"x\": 3");
        assert!(
            err.contains("objects[0].position[1].x (line 2, column"),
            "{err}"
        );
        assert!(err.contains("the file ends early"), "{err}");
        let err = e(r#"{"objects": [{"position": [{"x": NaN, "y": 2}]}]}"#);
        assert!(err.contains("objects[0].position[0].x"), "{err}");
        assert!(err.contains("NaN and Infinity are not JSON"), "{err}");
        let err = e(r#"{"objects": [{"position": [], "heading": []}], "roads": []}"#);
        assert!(err.contains("x.json: objects[0] (line 1"), "{err}");
        assert!(err.contains("missing field `velocity`"), "{err}");
        let err = e(r#"{"objects": [], "roads": []}"#);
        assert!(err.contains("x.json: objects: is empty"), "{err}");
        let text = r#"{"a": [1, {"b\"c": [0, "#;
        assert_eq!(json_path(text, text.len()), "a[1].b\\\"c[1]");
    }

    /// GPUDrive's example files (WOMD-derived, so not in this repository), read from
    /// `$DRIVESCRIPT_GPUDRIVE_DIR` when it is set: each must read, through the loader's
    /// dispatch, with agents, lanes, and a lane graph that joins most lanes and turns through
    /// a junction. Prints "skipped" without it.
    #[test]
    fn gpudrive_example_files_when_given() {
        let Some(dir) = std::env::var_os("DRIVESCRIPT_GPUDRIVE_DIR")
            .map(std::path::PathBuf::from)
            .filter(|d| d.is_dir())
        else {
            eprintln!("skipped: DRIVESCRIPT_GPUDRIVE_DIR is not a directory");
            return;
        };
        let mut files: Vec<_> = std::fs::read_dir(&dir)
            .unwrap()
            .map(|e| e.unwrap().path())
            .filter(|p| p.extension().is_some_and(|e| e == "json"))
            .collect();
        files.sort();
        assert!(!files.is_empty(), "no .json files in {}", dir.display());
        for f in files {
            assert_eq!(
                crate::io::detect_format(&f).unwrap(),
                crate::io::SceneFormat::Gpudrive
            );
            let s = crate::io::load_scene(&f, 0, &crate::io::LoadOptions::default()).unwrap();
            let g = s.map.graph();
            let lanes = s.map.lanes();
            let joined = lanes
                .iter()
                .filter(|l| !g.successors(l.id).is_empty())
                .count();
            let entered = lanes
                .iter()
                .filter(|l| !g.predecessors(l.id).is_empty())
                .count();
            // A turn: a lane with a predecessor and a successor whose direction changes by
            // more than 60 degrees from its start to its end.
            let turns = lanes
                .iter()
                .filter(|l| {
                    let c = &l.centerline;
                    let (a, b) = (
                        c.segment_direction(0),
                        c.segment_direction(c.segment_count() - 1),
                    );
                    !g.successors(l.id).is_empty()
                        && !g.predecessors(l.id).is_empty()
                        && a.dot(&b) < 0.5
                })
                .count();
            let count = |t| s.agents.iter().filter(|a| a.agent_type == t).count();
            eprintln!(
                "{}: scenario {}, {} agents ({} vehicles, {} pedestrians, {} cyclists, {} \
                 other), {} valid at step {}, ego {:?}; {} lanes, {} with successors, {} with \
                 predecessors, {} successor links, {} turns joined at both ends; warnings: {:?}",
                f.file_name().unwrap().to_string_lossy(),
                s.meta.scenario_id,
                s.agents.len(),
                count(AgentType::Vehicle),
                count(AgentType::Pedestrian),
                count(AgentType::Cyclist),
                count(AgentType::Other),
                s.agents
                    .iter()
                    .filter(|a| a.is_valid(s.meta.current_step))
                    .count(),
                s.meta.current_step,
                s.meta.ego,
                lanes.len(),
                joined,
                entered,
                g.edge_counts().successor,
                turns,
                s.meta.warnings
            );
            assert_eq!((s.num_steps(), s.meta.current_step), (91, 10));
            assert!(s.meta.ego.is_some());
            assert!(joined * 2 > lanes.len(), "most lanes lead somewhere");
            assert!(turns > 0, "a route turns through a junction");
        }
    }

    #[test]
    fn only_json_with_objects_or_roads_is_taken_for_a_scenario() {
        let dir = tempfile::tempdir().unwrap();
        let w = |name: &str, text: &str| {
            let p = dir.path().join(name);
            std::fs::write(&p, text).unwrap();
            is_scenario_file(&p)
        };
        assert!(w("a.json", r#"{"name": "x", "objects": [], "roads": []}"#));
        assert!(w("b.json", r#"{"roads": [{"geometry": ["#));
        assert!(!w(
            "c.json",
            r#"{"lane_segments": {}, "drivable_areas": {}}"#
        ));
        assert!(!w(
            "d.json",
            r#"{"format": "drivescript-rollout", "agents": []}"#
        ));
        assert!(!w("e.json", "[1, 2]"));
        assert!(!w("f.json", ""));
        assert!(!is_scenario_file(&dir.path().join("missing.json")));
    }
}
