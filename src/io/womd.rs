//! Waymo Open Motion Dataset: `Scenario` protos in TFRecord files, one scenario per record.
//!
//! Read: tracks become agents (size from the current state, else the first valid one), lane
//! centres become lanes (entry/exit lanes → predecessors/successors, same-direction neighbours
//! → left/right), road edges keep WOMD's orientation (road on the left), road lines, crosswalks,
//! speed bumps and stop signs are kept. Traffic-signal states and driveways are not part of the
//! scene model; the reader says so in the scene's warnings. WOMD lanes carry boundaries as
//! references into road lines, not as their own polylines, so WOMD lanes have no boundaries.

use std::io::BufReader;
use std::path::{Path, PathBuf};

use prost::Message;

use super::tfrecord::{frame_records, TfRecordReader};
use super::womd_proto as pb;
use super::IoError;
use crate::geom::{Point, Polygon, Polyline};
use crate::scene::{
    Agent, AgentState, AgentType, Lane, LaneType, Map, MapParts, RoadEdge, RoadEdgeKind, RoadLine,
    RoadLineKind, Scene, SceneMeta, SourceFormat, StopLine,
};

const MPH_TO_MPS: f64 = 0.44704;

/// Whether a directory holds WOMD shards (files named like TFRecords).
pub fn is_shard_dir(dir: &Path) -> bool {
    shard_files(dir).is_ok_and(|v| !v.is_empty())
}

/// Whether a (lower-case) file name is one WOMD gives its shards, extension or not.
pub fn is_shard_name(name: &str) -> bool {
    name.ends_with(".tfrecord") || name.contains(".tfrecord-") || name.starts_with("tfrecord-")
}

/// The shards of a directory that holds nothing but shards (and files of no scene format): a
/// directory with other scene files beside a shard is not a shard directory, so that each of
/// its files is read on its own instead of the shard hiding them.
fn shard_files(dir: &Path) -> Result<Vec<PathBuf>, IoError> {
    let mut files = Vec::new();
    let mut jsons = Vec::new();
    for e in std::fs::read_dir(dir).map_err(|e| IoError::read(dir, e))? {
        let Ok(e) = e else { continue };
        let p = e.path();
        if !p.is_file() {
            continue;
        }
        let name = e.file_name().to_string_lossy().to_lowercase();
        let other_scene = [".xml", ".xml.gz", ".yaml", ".yml", ".parquet"]
            .iter()
            .any(|x| name.ends_with(x));
        if other_scene {
            return Ok(Vec::new());
        }
        // GPUDrive names its JSON after the shard it came from
        // (`tfrecord-00000-of-01000_4.json`): JSON is never a shard, and a GPUDrive scenario
        // is another scene file. Only looked into when there are shards to hide it.
        if name.ends_with(".json") {
            jsons.push(p);
        } else if is_shard_name(&name) {
            files.push(p);
        }
    }
    if !files.is_empty() && jsons.iter().any(|p| super::gpudrive::is_scenario_file(p)) {
        return Ok(Vec::new());
    }
    files.sort();
    Ok(files)
}

/// Streams the scenarios of one TFRecord file.
pub fn read_file(path: &Path) -> Result<impl Iterator<Item = Result<Scene, IoError>>, IoError> {
    // Read record by record, each within its own cap: the file as a whole may be large.
    let file = super::open_regular(path, u64::MAX, "a TFRecord file")?;
    if file.metadata().map_err(|e| IoError::read(path, e))?.len() == 0 {
        return Err(IoError::invalid(
            path,
            "file",
            "empty: a WOMD file holds at least one record",
        ));
    }
    let path = path.to_path_buf();
    let reader = TfRecordReader::new(BufReader::with_capacity(1 << 20, file));
    Ok(reader.enumerate().map(move |(i, rec)| {
        let bytes = rec.map_err(|e| {
            let mut fault = e.fault();
            // A file that fails on its first record may be no TFRecord at all: say what it is.
            if e.record() == 0 {
                if let Some(c) = super::sniff(&path).filter(|c| *c != super::Content::TfRecord) {
                    fault.push_str(&format!(" (the file is {}, not a TFRecord)", c.describe()));
                }
            }
            IoError::invalid(&path, e.location(), fault)
        })?;
        decode_record(&path, i, &bytes)
    }))
}

/// Streams the scenarios of every shard in a directory, in file-name order.
pub fn read_shards(dir: &Path) -> Result<impl Iterator<Item = Result<Scene, IoError>>, IoError> {
    let files = shard_files(dir)?;
    Ok(files
        .into_iter()
        .flat_map(|f| -> Box<dyn Iterator<Item = Result<Scene, IoError>>> {
            match read_file(&f) {
                Ok(it) => Box::new(it),
                Err(e) => Box::new(std::iter::once(Err(e))),
            }
        }))
}

/// Decodes record `index` of `path` into a scene.
pub fn decode_record(path: &Path, index: usize, bytes: &[u8]) -> Result<Scene, IoError> {
    let loc = format!("record {index}");
    let scenario = super::womd_wire::decode_scenario(bytes)
        .map_err(|e| IoError::invalid(path, &loc, format!("not a Scenario proto: {e}")))?;
    scenario_to_scene(&scenario, path, index)
}

fn pt(p: &pb::MapPoint) -> Point {
    Point::new(p.x.unwrap_or(0.0), p.y.unwrap_or(0.0))
}

/// Converts a decoded scenario (record `index` of `path`) into a scene.
pub fn scenario_to_scene(sc: &pb::Scenario, path: &Path, index: usize) -> Result<Scene, IoError> {
    let id = sc.scenario_id.clone().unwrap_or_default();
    let loc = format!("record {index} (scenario {id})");
    let bad = |msg: String| IoError::invalid(path, &loc, msg);
    let steps = sc.timestamps_seconds.len();
    let mut warnings = Vec::new();

    if steps == 0 {
        return Err(bad("no timestamps: an empty scenario".into()));
    }
    let dt = if steps >= 2 {
        let mut diffs: Vec<f64> = sc
            .timestamps_seconds
            .windows(2)
            .map(|w| w[1] - w[0])
            .collect();
        diffs.sort_by(f64::total_cmp);
        let dt = diffs[diffs.len() / 2];
        // The scene model has one time step: a gap or a jump back would be read as motion
        // at the wrong speed. WOMD's own jitter is far below 10 %.
        if !(dt.is_finite() && dt > 0.0) {
            return Err(bad(format!(
                "timestamps do not increase (median step {dt} s)"
            )));
        }
        if let Some(k) = sc
            .timestamps_seconds
            .windows(2)
            .position(|w| ((w[1] - w[0]) - dt).abs() > 0.1 * dt)
        {
            let (a, b) = (sc.timestamps_seconds[k], sc.timestamps_seconds[k + 1]);
            return Err(bad(format!(
                "timestamps jump from {a} s to {b} s at step {k} where every other step is {dt:.3} s: \
                 a gap or reordering the scene model cannot represent"
            )));
        }
        dt
    } else {
        0.1
    };
    let current = sc.current_time_index.unwrap_or(0);
    if current < 0 || (steps > 0 && current as usize >= steps) {
        return Err(bad(format!(
            "current_time_index {current} is outside the {steps} timestamps"
        )));
    }

    super::check_states(path, &loc, sc.tracks.len(), steps)?;
    let mut agents = Vec::with_capacity(sc.tracks.len());
    for (ti, track) in sc.tracks.iter().enumerate() {
        let tid = track
            .id
            .ok_or_else(|| bad(format!("track {ti} has no id")))?;
        if track.states.len() != steps {
            return Err(bad(format!(
                "track {ti} (id {tid}) has {} states for {steps} timestamps",
                track.states.len()
            )));
        }
        let agent_type = match track.object_type.unwrap_or(0) {
            pb::object_type::VEHICLE => AgentType::Vehicle,
            pb::object_type::PEDESTRIAN => AgentType::Pedestrian,
            pb::object_type::CYCLIST => AgentType::Cyclist,
            _ => AgentType::Other,
        };
        let valid = |s: &pb::ObjectState| s.valid.unwrap_or(false);
        let size_src = track
            .states
            .get(current as usize)
            .filter(|s| valid(s))
            .or_else(|| track.states.iter().find(|s| valid(s)));
        let (length, width) = size_src.map_or((0.0, 0.0), |s| {
            (
                s.length.unwrap_or(0.0) as f64,
                s.width.unwrap_or(0.0) as f64,
            )
        });
        let states = track
            .states
            .iter()
            .map(|s| {
                if valid(s) {
                    AgentState {
                        x: s.center_x.unwrap_or(0.0),
                        y: s.center_y.unwrap_or(0.0),
                        heading: s.heading.unwrap_or(0.0) as f64,
                        vx: s.velocity_x.unwrap_or(0.0) as f64,
                        vy: s.velocity_y.unwrap_or(0.0) as f64,
                        valid: true,
                    }
                } else {
                    AgentState::INVALID
                }
            })
            .collect();
        agents.push(Agent {
            id: tid as i64,
            agent_type,
            length,
            width,
            states,
            is_static: false,
        });
    }
    let ego = match sc.sdc_track_index {
        Some(i) => Some(
            agents
                .get(i as usize)
                .ok_or_else(|| {
                    bad(format!(
                        "sdc_track_index {i} but only {} tracks",
                        agents.len()
                    ))
                })?
                .id,
        ),
        None => None,
    };

    let mut parts = MapParts::default();
    let mut driveways = 0;
    for f in &sc.map_features {
        let fid = f.id.unwrap_or(-1);
        let line = |pts: &[pb::MapPoint], what: &str| -> Result<Option<Polyline>, IoError> {
            match Polyline::new(pts.iter().map(pt)) {
                Ok(l) => Ok(Some(l)),
                Err(crate::geom::GeomError::TooFewPoints { got, .. }) => {
                    let _ = got;
                    Ok(None)
                }
                Err(e) => Err(bad(format!("{what} {fid}: {e}"))),
            }
        };
        match &f.feature_data {
            Some(pb::FeatureData::Lane(l)) => {
                let Some(center) = line(&l.polyline, "lane")? else {
                    warnings.push(format!(
                        "lane {fid} skipped: its polyline has fewer than 2 distinct points"
                    ));
                    continue;
                };
                let mut lane = Lane::new(fid, center);
                lane.lane_type = match l.r#type.unwrap_or(0) {
                    pb::lane_type::FREEWAY => LaneType::Freeway,
                    pb::lane_type::SURFACE_STREET => LaneType::SurfaceStreet,
                    pb::lane_type::BIKE_LANE => LaneType::Bike,
                    _ => LaneType::Other,
                };
                lane.speed_limit = l
                    .speed_limit_mph
                    .filter(|v| *v > 0.0)
                    .map(|v| v * MPH_TO_MPS);
                // WOMD: lane centres in intersections have no boundaries.
                lane.is_intersection =
                    l.left_boundaries.is_empty() && l.right_boundaries.is_empty();
                lane.predecessors = l.entry_lanes.clone();
                lane.successors = l.exit_lanes.clone();
                lane.left_neighbors = l
                    .left_neighbors
                    .iter()
                    .filter_map(|n| n.feature_id)
                    .collect();
                lane.right_neighbors = l
                    .right_neighbors
                    .iter()
                    .filter_map(|n| n.feature_id)
                    .collect();
                parts.lanes.push(lane);
            }
            Some(pb::FeatureData::RoadEdge(e)) => {
                let Some(l) = line(&e.polyline, "road edge")? else {
                    warnings.push(format!(
                        "road edge {fid} skipped: fewer than 2 distinct points"
                    ));
                    continue;
                };
                let kind = match e.r#type.unwrap_or(0) {
                    pb::road_edge_type::BOUNDARY => RoadEdgeKind::Boundary,
                    pb::road_edge_type::MEDIAN => RoadEdgeKind::Median,
                    _ => RoadEdgeKind::Unknown,
                };
                parts.road_edges.push(RoadEdge::new(kind, l));
            }
            Some(pb::FeatureData::RoadLine(r)) => {
                let Some(l) = line(&r.polyline, "road line")? else {
                    warnings.push(format!(
                        "road line {fid} skipped: fewer than 2 distinct points"
                    ));
                    continue;
                };
                use pb::road_line_type as t;
                let ty = r.r#type.unwrap_or(0);
                let kind = match ty {
                    t::BROKEN_SINGLE_WHITE | t::BROKEN_SINGLE_YELLOW | t::BROKEN_DOUBLE_YELLOW => {
                        RoadLineKind::Broken
                    }
                    t::SOLID_SINGLE_WHITE | t::SOLID_SINGLE_YELLOW => RoadLineKind::Solid,
                    t::SOLID_DOUBLE_WHITE | t::SOLID_DOUBLE_YELLOW | t::PASSING_DOUBLE_YELLOW => {
                        RoadLineKind::DoubleSolid
                    }
                    _ => RoadLineKind::Unknown,
                };
                parts.road_lines.push(RoadLine {
                    kind,
                    yellow: (t::BROKEN_SINGLE_YELLOW..=t::PASSING_DOUBLE_YELLOW).contains(&ty),
                    line: l,
                });
            }
            Some(pb::FeatureData::StopSign(s)) => {
                let Some(p) = &s.position else {
                    warnings.push(format!("stop sign {fid} skipped: no position"));
                    continue;
                };
                parts.stop_lines.push(StopLine {
                    points: vec![pt(p)],
                    lanes: s.lane.clone(),
                });
            }
            Some(pb::FeatureData::Crosswalk(c)) => match Polygon::new(c.polygon.iter().map(pt)) {
                Ok(p) => parts.crosswalks.push(p),
                Err(e) => warnings.push(format!("crosswalk {fid} skipped: {e}")),
            },
            Some(pb::FeatureData::SpeedBump(c)) => match Polygon::new(c.polygon.iter().map(pt)) {
                Ok(p) => parts.speed_bumps.push(p),
                Err(e) => warnings.push(format!("speed bump {fid} skipped: {e}")),
            },
            Some(pb::FeatureData::Driveway(_)) => driveways += 1,
            None => warnings.push(format!("map feature {fid} has no data")),
        }
    }
    if driveways > 0 {
        warnings.push(format!(
            "{driveways} driveways not represented in the scene model"
        ));
    }
    let signals = sc
        .dynamic_map_states
        .iter()
        .map(|d| d.lane_states.len())
        .sum::<usize>();
    if signals > 0 {
        warnings.push(format!(
            "{signals} traffic-signal lane states not represented in the scene model"
        ));
    }

    warnings.extend(super::turning_back_warning(&parts.lanes));
    let map = Map::new(parts).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        location: loc.clone(),
        error: e,
    })?;
    let meta = SceneMeta {
        source_format: SourceFormat::Womd,
        source_file: path.display().to_string(),
        scenario_id: if id.is_empty() {
            format!("{}#{index}", super::file_stem(path))
        } else {
            id
        },
        dt,
        current_step: current as usize,
        ego,
        warnings,
    };
    Scene::recorded(meta, map, agents).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        location: loc,
        error: e,
    })
}

fn map_point(p: Point) -> pb::MapPoint {
    pb::MapPoint {
        x: Some(p.x),
        y: Some(p.y),
        z: Some(0.0),
    }
}

/// Encodes a scene as a WOMD `Scenario` (lanes, edges, lines, crosswalks, speed bumps, stop
/// signs, tracks). Used to write test shards and to convert other datasets for WOMD tools.
/// Agent ids must fit the format's 32-bit track ids, as [`write_file`] checks.
pub fn scene_to_scenario(scene: &Scene) -> pb::Scenario {
    let steps = scene.num_steps();
    let tracks: Vec<pb::Track> = scene
        .agents
        .iter()
        .map(|a| pb::Track {
            // Checked by `write_file`; ids in range convert exactly.
            id: Some(a.id as i32),
            object_type: Some(match a.agent_type {
                AgentType::Vehicle => pb::object_type::VEHICLE,
                AgentType::Pedestrian => pb::object_type::PEDESTRIAN,
                AgentType::Cyclist => pb::object_type::CYCLIST,
                AgentType::Other => pb::object_type::OTHER,
            }),
            states: a
                .states
                .iter()
                .map(|s| {
                    if s.valid {
                        pb::ObjectState {
                            center_x: Some(s.x),
                            center_y: Some(s.y),
                            center_z: Some(0.0),
                            length: Some(a.length as f32),
                            width: Some(a.width as f32),
                            height: Some(1.5),
                            heading: Some(s.heading as f32),
                            velocity_x: Some(s.vx as f32),
                            velocity_y: Some(s.vy as f32),
                            valid: Some(true),
                        }
                    } else {
                        pb::ObjectState {
                            center_x: Some(-1.0),
                            center_y: Some(-1.0),
                            center_z: Some(-1.0),
                            length: Some(-1.0),
                            width: Some(-1.0),
                            height: Some(-1.0),
                            heading: Some(-1.0),
                            velocity_x: Some(-1.0),
                            velocity_y: Some(-1.0),
                            valid: Some(false),
                        }
                    }
                })
                .collect(),
        })
        .collect();
    let mut features = Vec::new();
    let g = scene.map.graph();
    let neighbor = |id: i64| pb::LaneNeighbor {
        feature_id: Some(id),
        ..Default::default()
    };
    for lane in scene.map.lanes() {
        features.push(pb::MapFeature {
            id: Some(lane.id),
            feature_data: Some(pb::FeatureData::Lane(pb::LaneCenter {
                speed_limit_mph: lane.speed_limit.map(|v| v / MPH_TO_MPS),
                r#type: Some(match lane.lane_type {
                    LaneType::Freeway => pb::lane_type::FREEWAY,
                    LaneType::SurfaceStreet | LaneType::Bus => pb::lane_type::SURFACE_STREET,
                    LaneType::Bike => pb::lane_type::BIKE_LANE,
                    LaneType::Other => pb::lane_type::UNDEFINED,
                }),
                interpolating: Some(false),
                polyline: lane
                    .centerline
                    .points()
                    .iter()
                    .map(|p| map_point(*p))
                    .collect(),
                entry_lanes: g.predecessors(lane.id).to_vec(),
                exit_lanes: g.successors(lane.id).to_vec(),
                left_neighbors: g
                    .left_neighbors(lane.id)
                    .iter()
                    .map(|&i| neighbor(i))
                    .collect(),
                right_neighbors: g
                    .right_neighbors(lane.id)
                    .iter()
                    .map(|&i| neighbor(i))
                    .collect(),
                // Mark non-intersection lanes as bounded so that the reader's intersection
                // heuristic gives the flag back.
                left_boundaries: if lane.is_intersection {
                    vec![]
                } else {
                    vec![pb::BoundarySegment::default()]
                },
                right_boundaries: vec![],
            })),
        });
    }
    let mut next_id = scene.map.lanes().iter().map(|l| l.id).max().unwrap_or(0) + 1;
    let mut fresh = || {
        next_id += 1;
        Some(next_id)
    };
    for e in scene.map.road_edges() {
        features.push(pb::MapFeature {
            id: fresh(),
            feature_data: Some(pb::FeatureData::RoadEdge(pb::RoadEdge {
                r#type: Some(match e.kind {
                    RoadEdgeKind::Boundary => pb::road_edge_type::BOUNDARY,
                    RoadEdgeKind::Median => pb::road_edge_type::MEDIAN,
                    RoadEdgeKind::Unknown => pb::road_edge_type::UNKNOWN,
                }),
                polyline: e.line().points().iter().map(|p| map_point(*p)).collect(),
            })),
        });
    }
    for l in scene.map.road_lines() {
        use pb::road_line_type as t;
        let ty = match (l.kind, l.yellow) {
            (RoadLineKind::Broken, false) => t::BROKEN_SINGLE_WHITE,
            (RoadLineKind::Broken, true) => t::BROKEN_SINGLE_YELLOW,
            (RoadLineKind::Solid, false) => t::SOLID_SINGLE_WHITE,
            (RoadLineKind::Solid, true) => t::SOLID_SINGLE_YELLOW,
            (RoadLineKind::DoubleSolid, false) => t::SOLID_DOUBLE_WHITE,
            (RoadLineKind::DoubleSolid, true) => t::SOLID_DOUBLE_YELLOW,
            (RoadLineKind::Unknown, _) => t::UNKNOWN,
        };
        features.push(pb::MapFeature {
            id: fresh(),
            feature_data: Some(pb::FeatureData::RoadLine(pb::RoadLine {
                r#type: Some(ty),
                polyline: l.line.points().iter().map(|p| map_point(*p)).collect(),
            })),
        });
    }
    for c in scene.map.crosswalks() {
        features.push(pb::MapFeature {
            id: fresh(),
            feature_data: Some(pb::FeatureData::Crosswalk(pb::Crosswalk {
                polygon: c.points().iter().map(|p| map_point(*p)).collect(),
            })),
        });
    }
    for c in scene.map.speed_bumps() {
        features.push(pb::MapFeature {
            id: fresh(),
            feature_data: Some(pb::FeatureData::SpeedBump(pb::SpeedBump {
                polygon: c.points().iter().map(|p| map_point(*p)).collect(),
            })),
        });
    }
    for s in scene.map.stop_lines() {
        let centre = s.points.iter().sum::<Point>() / s.points.len().max(1) as f64;
        features.push(pb::MapFeature {
            id: fresh(),
            feature_data: Some(pb::FeatureData::StopSign(pb::StopSign {
                lane: s.lanes.clone(),
                position: Some(map_point(centre)),
            })),
        });
    }
    pb::Scenario {
        scenario_id: Some(scene.meta.scenario_id.clone()),
        timestamps_seconds: (0..steps).map(|k| k as f64 * scene.meta.dt).collect(),
        current_time_index: Some(scene.meta.current_step as i32),
        sdc_track_index: scene
            .meta
            .ego
            .and_then(|e| scene.agents.iter().position(|a| a.id == e))
            .map(|i| i as i32),
        tracks,
        dynamic_map_states: vec![pb::DynamicMapState::default(); steps],
        map_features: features,
        objects_of_interest: vec![],
        tracks_to_predict: vec![],
    }
}

/// Writes scenes as one TFRecord file of `Scenario` records (atomically).
pub fn write_file(path: &Path, scenes: &[Scene]) -> Result<(), IoError> {
    // A track id is an int32 in the format: a wider id would wrap into another agent's.
    for s in scenes {
        if let Some(a) = s.agents.iter().find(|a| i32::try_from(a.id).is_err()) {
            return Err(IoError::invalid(
                path,
                format!("scene {}, agent {}", s.meta.scenario_id, a.id),
                format!(
                    "WOMD track ids are 32-bit ({} to {}); this id cannot be written",
                    i32::MIN,
                    i32::MAX
                ),
            ));
        }
    }
    let payloads: Vec<Vec<u8>> = scenes
        .iter()
        .map(|s| scene_to_scenario(s).encode_to_vec())
        .collect();
    super::write_atomic(path, &frame_records(&payloads))
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::io::tfrecord::frame_records;

    fn mp(x: f64, y: f64) -> pb::MapPoint {
        pb::MapPoint {
            x: Some(x),
            y: Some(y),
            z: Some(0.0),
        }
    }

    fn state(x: f64, valid: bool) -> pb::ObjectState {
        pb::ObjectState {
            center_x: Some(x),
            center_y: Some(1.8),
            center_z: Some(0.0),
            length: Some(4.5),
            width: Some(2.0),
            height: Some(1.6),
            heading: Some(0.0),
            velocity_x: Some(10.0),
            velocity_y: Some(0.0),
            valid: Some(valid),
        }
    }

    fn feature(id: i64, data: pb::FeatureData) -> pb::MapFeature {
        pb::MapFeature {
            id: Some(id),
            feature_data: Some(data),
        }
    }

    /// A scenario with every kind of map feature, encoded by prost as WOMD files are.
    pub(crate) fn scenario() -> pb::Scenario {
        let lane = |pts: Vec<pb::MapPoint>, exit: Vec<i64>, left: Vec<i64>| {
            pb::FeatureData::Lane(pb::LaneCenter {
                speed_limit_mph: Some(25.0),
                r#type: Some(pb::lane_type::SURFACE_STREET),
                interpolating: Some(false),
                polyline: pts,
                entry_lanes: vec![],
                exit_lanes: exit,
                left_boundaries: vec![pb::BoundarySegment {
                    lane_start_index: Some(0),
                    lane_end_index: Some(1),
                    boundary_feature_id: Some(30),
                    boundary_type: Some(pb::road_line_type::BROKEN_SINGLE_WHITE),
                }],
                right_boundaries: vec![],
                left_neighbors: left
                    .into_iter()
                    .map(|id| pb::LaneNeighbor {
                        feature_id: Some(id),
                        ..Default::default()
                    })
                    .collect(),
                right_neighbors: vec![],
            })
        };
        pb::Scenario {
            scenario_id: Some("abc123".into()),
            timestamps_seconds: (0..5).map(|k| k as f64 * 0.1).collect(),
            current_time_index: Some(2),
            tracks: vec![
                pb::Track {
                    id: Some(7),
                    object_type: Some(pb::object_type::VEHICLE),
                    states: (0..5).map(|k| state(k as f64, true)).collect(),
                },
                pb::Track {
                    id: Some(9),
                    object_type: Some(pb::object_type::PEDESTRIAN),
                    states: (0..5).map(|k| state(k as f64, k >= 3)).collect(),
                },
            ],
            dynamic_map_states: vec![
                pb::DynamicMapState {
                    lane_states: vec![pb::TrafficSignalLaneState {
                        lane: Some(1),
                        state: Some(6),
                        stop_point: Some(mp(50.0, 1.8)),
                    }],
                };
                5
            ],
            map_features: vec![
                feature(
                    1,
                    lane(vec![mp(0.0, 1.8), mp(50.0, 1.8)], vec![2, 99], vec![3]),
                ),
                feature(2, lane(vec![mp(50.0, 1.8), mp(100.0, 1.8)], vec![], vec![])),
                feature(3, lane(vec![mp(0.0, 5.4), mp(50.0, 5.4)], vec![], vec![])),
                feature(4, lane(vec![mp(3.0, 3.0)], vec![], vec![])),
                feature(
                    20,
                    pb::FeatureData::RoadEdge(pb::RoadEdge {
                        r#type: Some(pb::road_edge_type::BOUNDARY),
                        polyline: vec![mp(0.0, 0.0), mp(100.0, 0.0)],
                    }),
                ),
                feature(
                    30,
                    pb::FeatureData::RoadLine(pb::RoadLine {
                        r#type: Some(pb::road_line_type::SOLID_DOUBLE_YELLOW),
                        polyline: vec![mp(0.0, 7.2), mp(100.0, 7.2)],
                    }),
                ),
                feature(
                    40,
                    pb::FeatureData::StopSign(pb::StopSign {
                        lane: vec![1],
                        position: Some(mp(50.0, 0.0)),
                    }),
                ),
                feature(
                    50,
                    pb::FeatureData::Crosswalk(pb::Crosswalk {
                        polygon: vec![mp(60.0, 0.0), mp(64.0, 0.0), mp(64.0, 7.0), mp(60.0, 7.0)],
                    }),
                ),
                feature(
                    60,
                    pb::FeatureData::SpeedBump(pb::SpeedBump {
                        polygon: vec![mp(80.0, 0.0), mp(81.0, 0.0), mp(81.0, 7.0)],
                    }),
                ),
                feature(
                    70,
                    pb::FeatureData::Driveway(pb::Driveway {
                        polygon: vec![mp(0.0, -5.0), mp(5.0, -5.0), mp(5.0, 0.0)],
                    }),
                ),
            ],
            sdc_track_index: Some(0),
            objects_of_interest: vec![7, 9],
            tracks_to_predict: vec![pb::RequiredPrediction {
                track_index: Some(1),
                difficulty: Some(1),
            }],
        }
    }

    #[test]
    fn hand_encoded_scenario_reads_back() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("training.tfrecord-00000-of-00001");
        let bytes = scenario().encode_to_vec();
        std::fs::write(&path, frame_records(&[bytes.clone(), bytes])).unwrap();
        let scenes: Vec<Scene> = read_file(&path).unwrap().map(Result::unwrap).collect();
        assert_eq!(scenes.len(), 2);
        let s = &scenes[0];
        assert_eq!(s.meta.scenario_id, "abc123");
        assert_eq!(
            (s.num_steps(), s.meta.current_step, s.meta.ego),
            (5, 2, Some(7))
        );
        assert!((s.meta.dt - 0.1).abs() < 1e-12);
        let ped = s.agent(9).unwrap();
        assert_eq!(ped.agent_type, AgentType::Pedestrian);
        assert_eq!(ped.valid_span(), Some((3, 4)));
        assert_eq!((ped.length, ped.width), (4.5, 2.0));
        let lane = s.map.lane(1).unwrap();
        assert!((lane.speed_limit.unwrap() - 25.0 * MPH_TO_MPS).abs() < 1e-9);
        assert!(!lane.is_intersection);
        assert_eq!(s.map.graph().successors(1), &[2]);
        assert_eq!(s.map.graph().left(1), Some(3));
        assert_eq!(
            s.map.graph().dangling(),
            1,
            "exit lane 99 is outside the map"
        );
        assert_eq!(s.map.lanes().len(), 3, "the one-point lane 4 is skipped");
        assert_eq!(s.map.road_edges().len(), 1);
        assert_eq!(s.map.road_lines()[0].kind, RoadLineKind::DoubleSolid);
        assert!(s.map.road_lines()[0].yellow);
        assert_eq!(
            (s.map.crosswalks().len(), s.map.speed_bumps().len()),
            (1, 1)
        );
        assert_eq!(s.map.stop_lines()[0].lanes, vec![1]);
        let w = s.meta.warnings.join("\n");
        assert!(w.contains("lane 4 skipped"), "{w}");
        assert!(w.contains("1 driveways"), "{w}");
        assert!(w.contains("5 traffic-signal lane states"), "{w}");
    }

    #[test]
    fn scene_to_scenario_round_trips() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("a.tfrecord");
        std::fs::write(&path, frame_records(&[scenario().encode_to_vec()])).unwrap();
        let s = read_file(&path).unwrap().next().unwrap().unwrap();
        let out = dir.path().join("b.tfrecord");
        write_file(&out, std::slice::from_ref(&s)).unwrap();
        let back = read_file(&out).unwrap().next().unwrap().unwrap();
        assert_eq!(back.agents.len(), s.agents.len());
        for (a, b) in s.agents.iter().zip(&back.agents) {
            assert_eq!(
                (a.id, a.agent_type, a.valid_span()),
                (b.id, b.agent_type, b.valid_span())
            );
            for (x, y) in a.states.iter().zip(&b.states) {
                assert!((x.x - y.x).abs() < 1e-9 && (x.heading - y.heading).abs() < 1e-6);
            }
        }
        assert_eq!(back.map.lanes().len(), s.map.lanes().len());
        assert_eq!(back.map.graph().edge_counts(), s.map.graph().edge_counts());
        assert_eq!(back.map.road_lines()[0].kind, RoadLineKind::DoubleSolid);
        assert_eq!(back.meta.ego, Some(7));
    }

    #[test]
    fn bad_records_name_the_record() {
        let dir = tempfile::tempdir().unwrap();
        let good = scenario().encode_to_vec();
        let path = dir.path().join("x.tfrecord");
        // Framing is fine but record 1 is not a protobuf message.
        std::fs::write(&path, frame_records(&[good.clone(), vec![0xff; 40]])).unwrap();
        let results: Vec<_> = read_file(&path).unwrap().collect();
        assert!(results[0].is_ok());
        let e = results[1].as_ref().unwrap_err().to_string();
        assert!(
            e.contains("record 1") && e.contains("not a Scenario proto"),
            "{e}"
        );
        // A track whose state count disagrees with the timestamps.
        let mut sc = scenario();
        sc.tracks[1].states.pop();
        std::fs::write(&path, frame_records(&[good, sc.encode_to_vec()])).unwrap();
        let e = read_file(&path)
            .unwrap()
            .nth(1)
            .unwrap()
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("record 1") && e.contains("track 1 (id 9) has 4 states"),
            "{e}"
        );
        // A bit flip in record 1's payload.
        let mut bytes = frame_records(&[scenario().encode_to_vec(), scenario().encode_to_vec()]);
        let n = bytes.len();
        bytes[n - 30] ^= 0x04;
        std::fs::write(&path, &bytes).unwrap();
        let e = read_file(&path)
            .unwrap()
            .nth(1)
            .unwrap()
            .unwrap_err()
            .to_string();
        assert!(e.contains("record 1") && e.contains("checksum"), "{e}");
    }

    #[test]
    fn shard_directories_stream_in_name_order() {
        let dir = tempfile::tempdir().unwrap();
        let mut sc = scenario();
        for k in 0..3 {
            sc.scenario_id = Some(format!("s{k}"));
            let name = format!("validation.tfrecord-0000{k}-of-00003");
            std::fs::write(dir.path().join(name), frame_records(&[sc.encode_to_vec()])).unwrap();
        }
        std::fs::write(dir.path().join("README.txt"), "not a shard").unwrap();
        assert!(is_shard_dir(dir.path()));
        let ids: Vec<String> = read_shards(dir.path())
            .unwrap()
            .map(|s| s.unwrap().meta.scenario_id)
            .collect();
        assert_eq!(ids, vec!["s0", "s1", "s2"]);
    }
}
