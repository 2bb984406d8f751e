//! Argoverse 2 motion forecasting: a scenario parquet file plus the log map JSON beside it.
//!
//! Tracks become agents. AV2 records no object sizes, so agents get nominal footprints by type
//! (listed in [`nominal_size`]) and the scene's warnings say so. Non-numeric track ids (the
//! ego vehicle is `"AV"`) get fresh integer ids, also listed in the warnings. The focal track
//! is the scene's ego; the current step is the last observed step. Lane segments become lanes
//! (neighbours kept only when they run the same way), drivable areas are kept as polygons and
//! their outlines, turned counter-clockwise, are the road edges.

use std::collections::{BTreeMap, HashMap};
use std::path::{Path, PathBuf};

use parquet::file::reader::{FileReader, SerializedFileReader};
use parquet::file::statistics::Statistics;
use parquet::record::Field;
use serde::Deserialize;

use super::IoError;
use crate::geom::{num, Point, Polygon, Polyline};
use crate::scene::{
    Agent, AgentState, AgentType, Lane, LaneType, Map, MapParts, RoadEdge, RoadEdgeKind, RoadLine,
    RoadLineKind, Scene, SceneMeta, SourceFormat,
};

/// The scenario id a file name carries: `scenario_ID.parquet` or `log_map_archive_ID.json`.
fn named_id<'a>(path: &'a Path, prefix: &str, suffix: &str) -> Option<&'a str> {
    path.file_name()?
        .to_str()?
        .strip_prefix(prefix)?
        .strip_suffix(suffix)
}

fn listing(paths: &[PathBuf]) -> String {
    paths
        .iter()
        .map(|p| p.file_name().unwrap_or_default().to_string_lossy())
        .collect::<Vec<_>>()
        .join(", ")
}

/// The map JSON of the scenario whose parquet is `parquet`, in `dir`: the one named with its
/// scenario id, or the only one there.
fn map_for(parquet: &Path, dir: &Path, maps: &[PathBuf]) -> Result<PathBuf, IoError> {
    let id = named_id(parquet, "scenario_", ".parquet");
    if let Some(m) = maps
        .iter()
        .find(|m| id.is_some() && named_id(m, "log_map_archive_", ".json") == id)
    {
        return Ok(m.clone());
    }
    match maps {
        [] => Err(IoError::invalid(
            dir,
            "directory",
            "no log_map_archive_*.json file",
        )),
        [one] => Ok(one.clone()),
        _ => Err(IoError::invalid(
            dir,
            "directory",
            format!(
                "{} map files ({}) and none is named for {}: which map is the scenario's?",
                maps.len(),
                listing(maps),
                parquet.display()
            ),
        )),
    }
}

fn scenario_files(dir: &Path) -> Result<(Vec<PathBuf>, Vec<PathBuf>), IoError> {
    let (mut parquets, mut maps) = (Vec::new(), Vec::new());
    for e in std::fs::read_dir(dir).map_err(|e| IoError::read(dir, e))? {
        let p = e.map_err(|e| IoError::read(dir, e))?.path();
        if named_id(&p, "scenario_", ".parquet").is_some() {
            parquets.push(p);
        } else if named_id(&p, "log_map_archive_", ".json").is_some() {
            maps.push(p);
        }
    }
    parquets.sort();
    maps.sort();
    Ok((parquets, maps))
}

/// Whether `dir` is meant as an AV2 scenario directory: it holds a `scenario_*.parquet`.
/// Whether it is a good one (one scenario, its map) is the reader's to say, by name.
pub fn is_scenario_dir(dir: &Path) -> bool {
    scenario_files(dir).is_ok_and(|(parquets, _)| !parquets.is_empty())
}

/// The scenario parquet and map JSON of an AV2 scenario directory: exactly one parquet, and
/// its map (named with its scenario id, or the only one).
pub fn find_scenario_in_dir(dir: &Path) -> Result<(PathBuf, PathBuf), IoError> {
    let (parquets, maps) = scenario_files(dir)?;
    match parquets.as_slice() {
        [] => Err(IoError::invalid(
            dir,
            "directory",
            "no scenario_*.parquet file",
        )),
        [one] => Ok((one.clone(), map_for(one, dir, &maps)?)),
        _ => Err(IoError::invalid(
            dir,
            "directory",
            format!(
                "{} scenario files ({}): name the parquet file to read",
                parquets.len(),
                listing(&parquets)
            ),
        )),
    }
}

/// Nominal footprint (length, width) per AV2 object type, metres.
pub fn nominal_size(object_type: &str) -> (f64, f64) {
    match object_type {
        "vehicle" => (4.5, 2.0),
        "bus" => (12.0, 2.6),
        "pedestrian" => (0.6, 0.6),
        "cyclist" | "motorcyclist" => (2.0, 0.8),
        "riderless_bicycle" => (1.8, 0.6),
        _ => (1.0, 1.0),
    }
}

fn agent_type(object_type: &str) -> AgentType {
    match object_type {
        "vehicle" | "bus" => AgentType::Vehicle,
        "pedestrian" => AgentType::Pedestrian,
        "cyclist" | "motorcyclist" => AgentType::Cyclist,
        _ => AgentType::Other,
    }
}

/// Reads an AV2 scenario from its directory or its parquet file.
pub fn read(path: &Path) -> Result<Scene, IoError> {
    let (parquet, map_json) = if path.is_dir() {
        find_scenario_in_dir(path)?
    } else {
        let dir = match path.parent() {
            Some(d) if !d.as_os_str().is_empty() => d,
            _ => Path::new("."),
        };
        let (_, maps) = scenario_files(dir)?;
        let m = map_for(path, dir, &maps).map_err(|e| match maps.is_empty() {
            true => IoError::invalid(
                path,
                "map",
                "no log_map_archive_*.json beside the parquet file",
            ),
            false => e,
        })?;
        (path.to_path_buf(), m)
    };
    let (map, map_warnings) = read_map(&map_json)?;
    let (agents, mut meta) = read_tracks(&parquet)?;
    meta.warnings.extend(map_warnings);
    // The ids in the file names are the scenario's: a map of another scenario would be read
    // as this one's without a word.
    for (file, named) in [
        (&parquet, named_id(&parquet, "scenario_", ".parquet")),
        (&map_json, named_id(&map_json, "log_map_archive_", ".json")),
    ] {
        if let Some(named) = named.filter(|n| *n != meta.scenario_id) {
            return Err(IoError::invalid(
                file,
                "file name",
                format!(
                    "named for scenario {}, but the scenario is {}",
                    super::name::shown(named),
                    super::name::shown(&meta.scenario_id)
                ),
            ));
        }
    }
    Scene::recorded(meta, map, agents).map_err(|e| IoError::Scene {
        path: parquet.display().to_string(),
        location: "scenario".into(),
        error: e,
    })
}

/// What a column chunk's statistics say its values are.
enum Range {
    Number(f64, f64),
    Integer(i64, i64),
    Constant(Vec<u8>),
}

impl Range {
    /// The value and the recorded range, when `field` lies outside it.
    fn refuses(&self, field: &Field) -> Option<(String, String)> {
        let outside = |v: f64, lo: f64, hi: f64| v.is_finite() && !(lo..=hi).contains(&v);
        match (self, field) {
            (&Range::Number(lo, hi), &Field::Double(v)) if outside(v, lo, hi) => {
                Some((num(v), format!("{} to {}", num(lo), num(hi))))
            }
            (&Range::Number(lo, hi), &Field::Float(v)) if outside(v as f64, lo, hi) => {
                Some((num(v as f64), format!("{} to {}", num(lo), num(hi))))
            }
            (&Range::Integer(lo, hi), &Field::Long(v)) if !(lo..=hi).contains(&v) => {
                Some((v.to_string(), format!("{lo} to {hi}")))
            }
            (&Range::Integer(lo, hi), &Field::Int(v)) if !(lo..=hi).contains(&(v as i64)) => {
                Some((v.to_string(), format!("{lo} to {hi}")))
            }
            (Range::Constant(c), Field::Str(v)) if v.as_bytes() != c.as_slice() => Some((
                format!("{v:?}"),
                format!("only {:?}", String::from_utf8_lossy(c)),
            )),
            _ => None,
        }
    }
}

#[derive(Default)]
struct Row {
    observed: Option<bool>,
    track_id: Option<String>,
    object_type: Option<String>,
    timestep: Option<i64>,
    x: Option<f64>,
    y: Option<f64>,
    heading: Option<f64>,
    vx: Option<f64>,
    vy: Option<f64>,
    scenario_id: Option<String>,
    focal: Option<String>,
    num_timestamps: Option<i64>,
}

fn read_tracks(path: &Path) -> Result<(Vec<Agent>, SceneMeta), IoError> {
    let file = super::open_regular(path, super::MAX_SCENE_BYTES, "a scene file")?;
    let reader = SerializedFileReader::new(file).map_err(|e| {
        IoError::invalid(path, "footer", format!("not a readable parquet file: {e}"))
    })?;
    // Parquet pages written without checksums (AV2's) cannot be verified, but each column
    // chunk records its smallest and largest value: a damaged value usually lies outside.
    let chunk_ranges = |g: usize| -> HashMap<String, Range> {
        reader
            .metadata()
            .row_group(g)
            .columns()
            .iter()
            .filter_map(|c| {
                let range = match c.statistics()? {
                    Statistics::Double(v) => Range::Number(*v.min_opt()?, *v.max_opt()?),
                    Statistics::Float(v) => {
                        Range::Number(*v.min_opt()? as f64, *v.max_opt()? as f64)
                    }
                    Statistics::Int64(v) => Range::Integer(*v.min_opt()?, *v.max_opt()?),
                    Statistics::Int32(v) => {
                        Range::Integer(*v.min_opt()? as i64, *v.max_opt()? as i64)
                    }
                    // Writers have ordered bytes differently; a column holding one value
                    // (scenario_id, focal_track_id) is checked whatever the order.
                    Statistics::ByteArray(v) if v.min_opt()? == v.max_opt()? => {
                        Range::Constant(v.min_opt()?.data().to_vec())
                    }
                    _ => return None,
                };
                Some((c.column_path().string(), range))
            })
            .collect()
    };
    let mut rows = Vec::new();
    let mut i = 0usize;
    for g in 0..reader.num_row_groups() {
        let ranges = chunk_ranges(g);
        let group = reader
            .get_row_group(g)
            .map_err(|e| IoError::invalid(path, format!("row group {g}"), e.to_string()))?;
        let iter = group
            .get_row_iter(None)
            .map_err(|e| IoError::invalid(path, "schema", e.to_string()))?;
        for row in iter {
            let row = row.map_err(|e| IoError::invalid(path, format!("row {i}"), e.to_string()))?;
            let mut r = Row::default();
            for (name, field) in row.get_column_iter() {
                if let Some(range) = ranges.get(name.as_str()) {
                    if let Some((value, recorded)) = range.refuses(field) {
                        return Err(IoError::invalid(
                            path,
                            format!("row {i}"),
                            format!(
                                "{name} = {value} lies outside what the file records for its column ({recorded}): the file is damaged"
                            ),
                        ));
                    }
                }
                let f = |v: &Field| match v {
                    Field::Double(d) => Some(*d),
                    Field::Float(d) => Some(*d as f64),
                    _ => None,
                };
                let int = |v: &Field| match v {
                    Field::Long(d) => Some(*d),
                    Field::Int(d) => Some(*d as i64),
                    Field::ULong(d) => i64::try_from(*d).ok(),
                    _ => None,
                };
                let s = |v: &Field| match v {
                    Field::Str(s) => Some(s.clone()),
                    _ => None,
                };
                match name.as_str() {
                    "observed" => {
                        r.observed = matches!(field, Field::Bool(true))
                            .then_some(true)
                            .or(Some(false))
                    }
                    "track_id" => r.track_id = s(field),
                    "object_type" => r.object_type = s(field),
                    "timestep" => r.timestep = int(field),
                    "position_x" => r.x = f(field),
                    "position_y" => r.y = f(field),
                    "heading" => r.heading = f(field),
                    "velocity_x" => r.vx = f(field),
                    "velocity_y" => r.vy = f(field),
                    "scenario_id" => r.scenario_id = s(field),
                    "focal_track_id" => r.focal = s(field),
                    "num_timestamps" => r.num_timestamps = int(field),
                    _ => {}
                }
            }
            let missing = [
                ("track_id", r.track_id.is_none()),
                ("object_type", r.object_type.is_none()),
                ("timestep", r.timestep.is_none()),
                ("position_x", r.x.is_none()),
                ("position_y", r.y.is_none()),
                ("heading", r.heading.is_none()),
            ];
            if let Some((col, _)) = missing.iter().find(|(_, m)| *m) {
                return Err(IoError::invalid(
                    path,
                    format!("row {i}"),
                    format!("column {col} is missing or null"),
                ));
            }
            rows.push(r);
            i += 1;
        }
    }
    if rows.is_empty() {
        return Err(IoError::invalid(
            path,
            "rows",
            "the scenario has no track states",
        ));
    }
    let steps =
        rows.iter()
            .filter_map(|r| r.num_timestamps)
            .max()
            .unwrap_or(0)
            .max(rows.iter().filter_map(|r| r.timestep).max().unwrap_or(0) + 1) as usize;
    if steps > super::MAX_STEPS {
        return Err(IoError::invalid(
            path,
            "num_timestamps",
            format!("{steps} steps is implausible (limit {})", super::MAX_STEPS),
        ));
    }
    let mut warnings =
        vec!["AV2 has no object sizes: nominal footprints by type are used".to_string()];
    // Track ids in first-seen order; numeric ones keep their number.
    let mut order: Vec<String> = Vec::new();
    let mut tracks: HashMap<String, (String, Vec<AgentState>)> = HashMap::new();
    let mut current = 0usize;
    for (i, r) in rows.iter().enumerate() {
        let tid = r.track_id.clone().expect("checked");
        let t = r.timestep.expect("checked");
        if t < 0 || t as usize >= steps {
            return Err(IoError::invalid(
                path,
                format!("row {i}"),
                format!("timestep {t} outside 0..{steps}"),
            ));
        }
        if !tracks.contains_key(&tid) {
            super::check_states(path, &format!("row {i}"), tracks.len() + 1, steps)?;
        }
        let entry = tracks.entry(tid.clone()).or_insert_with(|| {
            order.push(tid.clone());
            (
                r.object_type.clone().expect("checked"),
                vec![AgentState::INVALID; steps],
            )
        });
        let (x, y, h) = (
            r.x.expect("checked"),
            r.y.expect("checked"),
            r.heading.expect("checked"),
        );
        if ![x, y, h].iter().all(|v| v.is_finite()) {
            return Err(IoError::invalid(
                path,
                format!("row {i}"),
                "non-finite position or heading",
            ));
        }
        if entry.1[t as usize].valid {
            return Err(IoError::invalid(
                path,
                format!("row {i}"),
                format!("track {tid} has a second state at timestep {t}"),
            ));
        }
        entry.1[t as usize] = AgentState {
            x,
            y,
            heading: h,
            vx: r.vx.filter(|v| v.is_finite()).unwrap_or(0.0),
            vy: r.vy.filter(|v| v.is_finite()).unwrap_or(0.0),
            valid: true,
        };
        if r.observed == Some(true) {
            current = current.max(t as usize);
        }
    }
    let mut next_id = order
        .iter()
        .filter_map(|t| t.parse::<i64>().ok())
        .max()
        .unwrap_or(0)
        + 1;
    let mut ids: BTreeMap<String, i64> = BTreeMap::new();
    for t in &order {
        let id = match t.parse::<i64>() {
            Ok(n) => n,
            Err(_) => {
                next_id += 1;
                warnings.push(format!("track {t:?} has id {}", next_id - 1));
                next_id - 1
            }
        };
        ids.insert(t.clone(), id);
    }
    let agents = order
        .iter()
        .map(|t| {
            let (ty, states) = tracks.remove(t).expect("present");
            let (length, width) = nominal_size(&ty);
            Agent {
                id: ids[t],
                agent_type: agent_type(&ty),
                length,
                width,
                states,
                is_static: ty == "static",
            }
        })
        .collect();
    let first = &rows[0];
    let meta = SceneMeta {
        source_format: SourceFormat::Av2,
        source_file: path.display().to_string(),
        scenario_id: first
            .scenario_id
            .clone()
            .unwrap_or_else(|| super::file_stem(path)),
        dt: 0.1,
        current_step: current,
        ego: first.focal.as_ref().and_then(|f| ids.get(f).copied()),
        warnings,
    };
    Ok((agents, meta))
}

#[derive(Deserialize)]
struct JsonPoint {
    x: f64,
    y: f64,
}

#[derive(Deserialize)]
struct JsonLane {
    id: i64,
    centerline: Vec<JsonPoint>,
    left_lane_boundary: Vec<JsonPoint>,
    right_lane_boundary: Vec<JsonPoint>,
    #[serde(default)]
    left_lane_mark_type: Option<String>,
    #[serde(default)]
    right_lane_mark_type: Option<String>,
    #[serde(default)]
    left_neighbor_id: Option<i64>,
    #[serde(default)]
    right_neighbor_id: Option<i64>,
    #[serde(default)]
    predecessors: Vec<i64>,
    #[serde(default)]
    successors: Vec<i64>,
    #[serde(default)]
    is_intersection: bool,
    #[serde(default)]
    lane_type: Option<String>,
}

#[derive(Deserialize)]
struct JsonArea {
    area_boundary: Vec<JsonPoint>,
}

#[derive(Deserialize)]
struct JsonCrossing {
    edge1: Vec<JsonPoint>,
    edge2: Vec<JsonPoint>,
}

#[derive(Deserialize)]
struct JsonMap {
    lane_segments: BTreeMap<String, JsonLane>,
    #[serde(default)]
    drivable_areas: BTreeMap<String, JsonArea>,
    #[serde(default)]
    pedestrian_crossings: BTreeMap<String, JsonCrossing>,
}

fn pts(v: &[JsonPoint]) -> Vec<Point> {
    v.iter().map(|p| Point::new(p.x, p.y)).collect()
}

/// The map of a `log_map_archive_*.json`, with what the scene's warnings should say of it.
fn read_map(path: &Path) -> Result<(Map, Vec<String>), IoError> {
    let text = super::read_text(path)?;
    // A lane segment, area or crossing keyed twice was read as its last copy: the first left
    // the map without a word.
    if let Err(e) = super::json::parse_json(&text) {
        if e.is_data() {
            return Err(IoError::invalid(
                path,
                format!("line {}, column {}", e.line(), e.column()),
                super::without_position(&e.to_string(), e.line(), e.column()),
            ));
        }
    }
    let m: JsonMap = serde_json::from_str(&text).map_err(|e| {
        IoError::invalid(
            path,
            format!("line {}, column {}", e.line(), e.column()),
            super::without_position(&e.to_string(), e.line(), e.column()),
        )
    })?;
    let mut parts = MapParts::default();
    let geom_err =
        |what: String, e: crate::geom::GeomError| IoError::invalid(path, what, e.to_string());
    let mut lines: Vec<(Polyline, String)> = Vec::new();
    let mut dirs: HashMap<i64, Point> = HashMap::new();
    let mut unknown_types: std::collections::BTreeMap<String, usize> = Default::default();
    // Read as written without a word before: a lane naming itself (the graph drops the
    // link), and one whose boundaries coincide (no surface).
    let (mut own_link, mut zero_width) = (Vec::new(), Vec::new());
    for (key, l) in &m.lane_segments {
        // AV2 keys each segment by its id: a key that differs (an edited file) made the
        // links that name one of the two point outside the map.
        if key.trim().parse::<i64>().ok() != Some(l.id) {
            return Err(IoError::invalid(
                path,
                format!("lane_segments[{}].id", super::name::shown(key)),
                format!(
                    "is {}, not the segment's key: AV2 keys each lane segment by its id",
                    l.id
                ),
            ));
        }
        if l.successors
            .iter()
            .chain(&l.predecessors)
            .chain(&l.left_neighbor_id)
            .chain(&l.right_neighbor_id)
            .any(|r| *r == l.id)
        {
            own_link.push(l.id.to_string());
        }
        let c = Polyline::new(pts(&l.centerline))
            .map_err(|e| geom_err(format!("lane_segments[{key}].centerline"), e))?;
        dirs.insert(l.id, c.last() - c.first());
        let mut lane = Lane::new(l.id, c);
        // A boundary of fewer than two distinct points is left out, as before; one with a
        // point beyond any map (1e300: a damaged file) was left out too, without a word,
        // where the same point in the centre line is refused.
        let boundary = |field: &str, points: &[JsonPoint]| match Polyline::new(pts(points)) {
            Ok(b) => Ok(Some(b)),
            Err(crate::geom::GeomError::TooFewPoints { .. }) => Ok(None),
            Err(e) => Err(geom_err(format!("lane_segments[{key}].{field}"), e)),
        };
        lane.left_boundary = boundary("left_lane_boundary", &l.left_lane_boundary)?;
        lane.right_boundary = boundary("right_lane_boundary", &l.right_lane_boundary)?;
        if let (Some(lb), Some(rb)) = (&lane.left_boundary, &lane.right_boundary) {
            if crate::scene::signed_width(lb, rb).0 < crate::scene::ZERO_WIDTH {
                zero_width.push(l.id.to_string());
            }
        }
        lane.lane_type = match l.lane_type.as_deref() {
            Some("VEHICLE") => LaneType::SurfaceStreet,
            Some("BIKE") => LaneType::Bike,
            Some("BUS") => LaneType::Bus,
            // AV2 has these three only: another (a damaged or edited file) made the lane one
            // of no known type without a word.
            Some(other) => {
                let shown = format!("\"{}\"", super::name::shown(other));
                *unknown_types.entry(shown).or_insert(0usize) += 1;
                LaneType::Other
            }
            None => LaneType::Other,
        };
        lane.is_intersection = l.is_intersection;
        lane.predecessors = l.predecessors.clone();
        lane.successors = l.successors.clone();
        lane.left_neighbors = l.left_neighbor_id.into_iter().collect();
        lane.right_neighbors = l.right_neighbor_id.into_iter().collect();
        for (b, mark) in [
            (&lane.left_boundary, &l.left_lane_mark_type),
            (&lane.right_boundary, &l.right_lane_mark_type),
        ] {
            if let (Some(b), Some(mark)) = (b, mark) {
                lines.push((b.clone(), mark.clone()));
            }
        }
        parts.lanes.push(lane);
    }
    // AV2 lists opposite-direction lanes as neighbours too; the lane graph wants same-direction.
    for lane in &mut parts.lanes {
        let own = dirs[&lane.id];
        let same = |n: &i64| dirs.get(n).is_some_and(|d| d.dot(&own) > 0.0);
        lane.left_neighbors.retain(same);
        lane.right_neighbors.retain(same);
    }
    let mut line_ends = super::RoadLineEnds::of(&parts.road_lines);
    for (line, mark) in lines {
        let kind = match mark.as_str() {
            "NONE" | "UNKNOWN" => continue,
            "DASHED_WHITE" | "DASHED_YELLOW" | "DOUBLE_DASH_WHITE" | "DOUBLE_DASH_YELLOW" => {
                RoadLineKind::Broken
            }
            "SOLID_WHITE" | "SOLID_YELLOW" | "SOLID_BLUE" => RoadLineKind::Solid,
            "DOUBLE_SOLID_WHITE" | "DOUBLE_SOLID_YELLOW" => RoadLineKind::DoubleSolid,
            _ => RoadLineKind::Unknown,
        };
        super::push_unique_road_line(
            &mut parts.road_lines,
            &mut line_ends,
            RoadLine {
                kind,
                yellow: mark.contains("YELLOW"),
                line,
            },
        );
    }
    for (key, a) in &m.drivable_areas {
        let poly = Polygon::new(pts(&a.area_boundary))
            .map_err(|e| geom_err(format!("drivable_areas[{key}]"), e))?;
        // Counter-clockwise outlines have the area on their left, the road-edge convention.
        let mut ring: Vec<Point> = poly.points().to_vec();
        if poly.signed_area() < 0.0 {
            ring.reverse();
        }
        ring.push(ring[0]);
        let edge =
            Polyline::new(ring).map_err(|e| geom_err(format!("drivable_areas[{key}]"), e))?;
        parts
            .road_edges
            .push(RoadEdge::new(RoadEdgeKind::Boundary, edge));
        parts.drivable_areas.push(poly);
    }
    for (key, c) in &m.pedestrian_crossings {
        let (e1, e2) = (pts(&c.edge1), pts(&c.edge2));
        let ring = e1.iter().chain(e2.iter().rev()).copied();
        parts.crosswalks.push(
            Polygon::new(ring).map_err(|e| geom_err(format!("pedestrian_crossings[{key}]"), e))?,
        );
    }
    let mut warnings: Vec<String> = unknown_types
        .iter()
        .map(|(t, n)| {
            format!(
                "map: {n} lane segment(s) of lane_type {t}, not one of AV2's (VEHICLE, BIKE, \
                 BUS): read as lanes of no known type"
            )
        })
        .collect();
    if !own_link.is_empty() {
        warnings.push(format!(
            "map: lane segment(s) {} name themselves as their own successor, predecessor or \
             neighbour: that link is dropped",
            super::first_few(&own_link)
        ));
    }
    if !zero_width.is_empty() {
        warnings.push(format!(
            "map: lane segment(s) {}: the boundaries coincide (zero width): no surface, so \
             nothing on it reads as on the lane",
            super::first_few(&zero_width)
        ));
    }
    if m.lane_segments.is_empty() {
        warnings.push(
            "map: no lane segments: no agent is on a lane, and lane-based script terms and the \
             model's lane inputs are empty"
                .into(),
        );
    }
    let map = Map::new(parts).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        location: "lane_segments".into(),
        error: e,
    })?;
    Ok((map, warnings))
}
