//! CommonRoad XML scenarios, 2018b (`<obstacle><role>dynamic</role>`) and 2020a
//! (`<dynamicObstacle>`), plain or gzipped.
//!
//! Lanelets become lanes: the centre line is the midpoint of the left and right bounds after
//! resampling both to the same number of points (one every 2 m at most); `adjacentLeft/Right`
//! with `drivingDir="same"` become neighbours. A bound with no lanelet beyond it (either
//! direction) is a road edge, except where it runs inside another lanelet (intersections).
//! Lanelet surfaces form the drivable area; crosswalk lanelets become crosswalks. Speed limits
//! come from `<speedLimit>` (2018b) or speed-limit traffic signs (2020a: `R2-1`, `274`).
//! Planning problems are not part of the scene model (their ego has no recorded trajectory).

use std::collections::HashMap;
use std::path::Path;

use roxmltree::{Document, Node};

use super::{IoError, LoadOptions};
use crate::geom::{CellIndex, Point, Polygon, Polyline};
use crate::scene::{
    Agent, AgentState, AgentType, Lane, LaneType, Map, MapParts, RoadEdge, RoadEdgeKind, RoadLine,
    RoadLineKind, Scene, SceneMeta, SourceFormat, StopLine,
};

/// Largest spacing of centre-line points, metres.
const CENTERLINE_SPACING: f64 = 2.0;

struct Ctx<'a> {
    path: &'a Path,
    doc: &'a Document<'a>,
}

impl Ctx<'_> {
    fn err(&self, node: Node, msg: impl Into<String>) -> IoError {
        let pos = self.doc.text_pos_at(node.range().start);
        let what = match node.attribute("id") {
            Some(id) => format!("<{} id={id}>", node.tag_name().name()),
            None => format!("<{}>", node.tag_name().name()),
        };
        IoError::invalid(
            self.path,
            format!("line {}, column {}, {what}", pos.row, pos.col),
            msg,
        )
    }

    fn child<'a, 'i>(&self, node: Node<'a, 'i>, name: &str) -> Option<Node<'a, 'i>> {
        node.children().find(|c| c.has_tag_name(name))
    }

    fn need<'a, 'i>(&self, node: Node<'a, 'i>, name: &str) -> Result<Node<'a, 'i>, IoError> {
        self.child(node, name)
            .ok_or_else(|| self.err(node, format!("missing <{name}>")))
    }

    fn number(&self, node: Node) -> Result<f64, IoError> {
        // Every text piece: `<x>20<!-- c -->.8465</x>` is 20.8465 to XML, and its first
        // piece alone was read as 20 without a word.
        let whole: String = node
            .children()
            .filter(|c| c.is_text())
            .filter_map(|c| c.text())
            .collect();
        let text = whole.trim();
        let v: f64 = text
            .parse()
            .map_err(|_| self.err(node, format!("expected a number, found {text:?}")))?;
        if !v.is_finite() {
            return Err(self.err(node, format!("{text} is not finite")));
        }
        Ok(v)
    }

    fn id(&self, node: Node, attr: &str) -> Result<i64, IoError> {
        let v = node
            .attribute(attr)
            .ok_or_else(|| self.err(node, format!("missing attribute {attr}")))?;
        v.trim()
            .parse()
            .map_err(|_| self.err(node, format!("attribute {attr}={v:?} is not an integer")))
    }

    /// A value given as `<exact>` or as an interval (its midpoint).
    fn value(&self, node: Node) -> Result<f64, IoError> {
        if let Some(e) = self.child(node, "exact") {
            return self.number(e);
        }
        match (
            self.child(node, "intervalStart"),
            self.child(node, "intervalEnd"),
        ) {
            (Some(a), Some(b)) => Ok(0.5 * (self.number(a)? + self.number(b)?)),
            _ => Err(self.err(node, "expected <exact> or <intervalStart>/<intervalEnd>")),
        }
    }

    fn point(&self, node: Node) -> Result<Point, IoError> {
        Ok(Point::new(
            self.number(self.need(node, "x")?)?,
            self.number(self.need(node, "y")?)?,
        ))
    }

    fn points(&self, node: Node) -> Result<Vec<Point>, IoError> {
        node.children()
            .filter(|c| c.has_tag_name("point"))
            .map(|p| self.point(p))
            .collect()
    }

    fn polyline(&self, node: Node) -> Result<Polyline, IoError> {
        Polyline::new(self.points(node)?).map_err(|e| self.err(node, e.to_string()))
    }
}

/// Reads one CommonRoad scenario.
pub fn read(path: &Path, opts: &LoadOptions) -> Result<Scene, IoError> {
    let bytes = super::read_maybe_gz(path)?;
    let text = std::str::from_utf8(&bytes)
        .map_err(|e| IoError::invalid(path, format!("byte {}", e.valid_up_to()), "not UTF-8"))?;
    parse(path, text, opts)
}

/// Deepest element nesting accepted (CommonRoad files nest about 8 deep). The XML parser
/// recurses per level: a file nested 200,000 deep overflowed the stack and aborted.
pub const MAX_XML_DEPTH: usize = 256;

/// The first position (byte offset) where elements nest deeper than `limit`, if any. Comments,
/// CDATA, processing instructions, declarations and quoted attribute values are skipped.
fn too_deep(text: &str, limit: usize) -> Option<usize> {
    let b = text.as_bytes();
    let skip_to = |from: usize, end: &[u8]| {
        b[from..]
            .windows(end.len())
            .position(|w| w == end)
            .map_or(b.len(), |k| from + k + end.len())
    };
    let (mut i, mut depth) = (0, 0usize);
    while i < b.len() {
        if b[i] != b'<' {
            i += 1;
            continue;
        }
        let rest = &b[i..];
        if rest.starts_with(b"<!--") {
            i = skip_to(i + 4, b"-->");
        } else if rest.starts_with(b"<![CDATA[") {
            i = skip_to(i + 9, b"]]>");
        } else if rest.starts_with(b"<?") {
            i = skip_to(i + 2, b"?>");
        } else if rest.starts_with(b"<!") {
            i = skip_to(i + 2, b">");
        } else if rest.starts_with(b"</") {
            depth = depth.saturating_sub(1);
            i = skip_to(i + 2, b">");
        } else {
            let (mut j, mut quote) = (i + 1, None);
            while j < b.len() {
                let c = b[j];
                match quote {
                    Some(q) if c == q => quote = None,
                    Some(_) => {}
                    None if c == b'"' || c == b'\'' => quote = Some(c),
                    None if c == b'>' => break,
                    None => {}
                }
                j += 1;
            }
            if j < b.len() && b[j - 1] != b'/' {
                depth += 1;
                if depth > limit {
                    return Some(i);
                }
            }
            i = j + 1;
        }
    }
    None
}

/// Parses CommonRoad XML text (`path` is used for messages and metadata).
pub fn parse(path: &Path, text: &str, opts: &LoadOptions) -> Result<Scene, IoError> {
    if let Some(at) = too_deep(text, MAX_XML_DEPTH) {
        let line = text[..at].matches('\n').count() + 1;
        return Err(IoError::invalid(
            path,
            format!("line {line}"),
            format!("elements nested more than {MAX_XML_DEPTH} deep"),
        ));
    }
    let doc = Document::parse(text).map_err(|e| {
        let pos = e.pos();
        IoError::invalid(
            path,
            format!("line {}, column {}", pos.row, pos.col),
            e.to_string(),
        )
    })?;
    let cx = Ctx { path, doc: &doc };
    let root = doc.root_element();
    if !root.has_tag_name("commonRoad") {
        return Err(cx.err(root, "the root element is not <commonRoad>"));
    }
    let dt: f64 = match root.attribute("timeStepSize") {
        Some(v) => v
            .trim()
            .parse()
            .map_err(|_| cx.err(root, format!("timeStepSize={v:?} is not a number")))?,
        None => return Err(cx.err(root, "missing attribute timeStepSize")),
    };
    let scenario_id = root
        .attribute("benchmarkID")
        .map(str::to_string)
        .unwrap_or_else(|| super::file_stem(path));

    let speed_signs = speed_limit_signs(&cx, root)?;
    let mut lanelet_notes = LaneletNotes::default();
    let map = read_map(&cx, root, &speed_signs, &mut lanelet_notes)?;
    let (agents, steps) = read_agents(&cx, root)?;
    let current_step = opts.commonroad_current_step.min(steps.saturating_sub(1));
    let meta = SceneMeta {
        source_format: SourceFormat::CommonRoad,
        source_file: path.display().to_string(),
        scenario_id,
        dt,
        current_step,
        ego: None,
        // A lanelet drawn out and back was read without a word, where WOMD and GPUDrive
        // lanes are warned of it.
        warnings: warnings(root)
            .into_iter()
            .chain(lanelet_notes.warnings())
            .chain(super::turning_back_warning(map.lanes()))
            .collect(),
    };
    Scene::recorded(meta, map, agents).map_err(|e| IoError::Scene {
        path: path.display().to_string(),
        location: "scenario".into(),
        error: e,
    })
}

/// Speed limits (m/s) of speed-limit traffic signs, by sign id.
fn speed_limit_signs(cx: &Ctx, root: Node) -> Result<HashMap<i64, f64>, IoError> {
    let mut out = HashMap::new();
    for sign in root.children().filter(|c| c.has_tag_name("trafficSign")) {
        for el in sign
            .children()
            .filter(|c| c.has_tag_name("trafficSignElement"))
        {
            let code = cx
                .child(el, "trafficSignID")
                .and_then(|n| n.text())
                .unwrap_or("")
                .trim();
            if code == "R2-1" || code == "274" {
                if let Some(v) = cx.child(el, "additionalValue") {
                    out.insert(cx.id(sign, "id")?, cx.number(v)?);
                }
            }
        }
    }
    Ok(out)
}

struct RawLanelet {
    id: i64,
    left: Polyline,
    right: Polyline,
    left_marking: Option<String>,
    right_marking: Option<String>,
    has_left: bool,
    has_right: bool,
    kind: LaneType,
    crosswalk: bool,
}

fn lane_type(name: &str) -> (LaneType, bool) {
    match name {
        "interstate" | "highway" | "mainCarriageWay" | "accessRamp" | "exitRamp" => {
            (LaneType::Freeway, false)
        }
        "urban" | "country" | "driveWay" | "unknown" => (LaneType::SurfaceStreet, false),
        "busLane" => (LaneType::Bus, false),
        "bicycleLane" => (LaneType::Bike, false),
        "crosswalk" => (LaneType::Other, true),
        _ => (LaneType::Other, false),
    }
}

fn centerline(left: &Polyline, right: &Polyline) -> Polyline {
    let len = left.length().max(right.length());
    // At most MAX_RESAMPLED_POINTS from the spacing: a bound running thousands of kilometres
    // (within the coordinate limit) made millions of points.
    let n = left.points().len().max(right.points().len()).max(
        ((len / CENTERLINE_SPACING).ceil() as usize + 1).min(crate::geom::MAX_RESAMPLED_POINTS),
    );
    let (l, r) = (left.resample_count(n), right.resample_count(n));
    let mid = l
        .points()
        .iter()
        .zip(r.points())
        .map(|(a, b)| (a + b) * 0.5);
    // Bounds that meet at both ends (a degenerate lanelet) fall back to the left bound.
    Polyline::new(mid).unwrap_or_else(|_| left.clone())
}

/// Lanelets the map reads other than as written, said once per scene with their ids.
#[derive(Default)]
struct LaneletNotes {
    /// Naming themselves as a successor, predecessor or neighbour: the graph drops the link.
    own_link: Vec<i64>,
    /// Left bound right of the driving direction: read with the bounds swapped back.
    swapped: Vec<i64>,
    /// Bounds that coincide: no surface, so nothing on it reads as on the road.
    zero_width: Vec<i64>,
    /// Successor or predecessor links between lanelets whose ends do not meet.
    far: Vec<crate::scene::FarLink>,
}

impl LaneletNotes {
    fn warnings(&self) -> Vec<String> {
        let ids = |v: &[i64]| {
            let all: Vec<String> = v.iter().map(i64::to_string).collect();
            format!(
                "lanelet{} {}",
                if v.len() == 1 { "" } else { "s" },
                super::first_few(&all)
            )
        };
        let mut out = Vec::new();
        if !self.own_link.is_empty() {
            out.push(format!(
                "{} name{} itself as its own successor, predecessor or neighbour: that link is \
                 dropped",
                ids(&self.own_link),
                if self.own_link.len() == 1 { "s" } else { "" }
            ));
        }
        if !self.swapped.is_empty() {
            out.push(format!(
                "{}: the leftBound lies right of the driving direction (bounds swapped): read \
                 with the bounds swapped back",
                ids(&self.swapped)
            ));
        }
        if !self.zero_width.is_empty() {
            out.push(format!(
                "{}: the bounds coincide (zero width): no surface, so nothing on it reads as on \
                 the road",
                ids(&self.zero_width)
            ));
        }
        if !self.far.is_empty() {
            let all: Vec<String> = self
                .far
                .iter()
                .map(|f| {
                    let (from, to) = if f.successor {
                        (f.lane, f.other)
                    } else {
                        (f.other, f.lane)
                    };
                    format!(
                        "{to} starts {} m from the end of {from}",
                        crate::geom::num((f.gap * 100.0).round() / 100.0)
                    )
                })
                .collect();
            out.push(format!(
                "lanelet links whose ends do not meet (over {} m apart), so a path along them \
                 jumps the gap: {}",
                crate::scene::LINK_GAP,
                super::first_few(&all)
            ));
        }
        out
    }
}

fn read_map(
    cx: &Ctx,
    root: Node,
    speed_signs: &HashMap<i64, f64>,
    notes: &mut LaneletNotes,
) -> Result<Map, IoError> {
    let mut parts = MapParts::default();
    let mut raws = Vec::new();
    let mut intersection_lanes = std::collections::HashSet::new();
    for inter in root.descendants().filter(|c| c.has_tag_name("incoming")) {
        for s in inter.children().filter(|c| {
            c.has_tag_name("successorsRight")
                || c.has_tag_name("successorsStraight")
                || c.has_tag_name("successorsLeft")
        }) {
            intersection_lanes.insert(cx.id(s, "ref")?);
        }
    }
    for node in root.children().filter(|c| c.has_tag_name("lanelet")) {
        let id = cx.id(node, "id")?;
        let lb = cx.need(node, "leftBound")?;
        let rb = cx.need(node, "rightBound")?;
        let mut left = cx.polyline(lb)?;
        let mut right = cx.polyline(rb)?;
        let marking = |b: Node| {
            cx.child(b, "lineMarking")
                .and_then(|m| m.text())
                .map(|t| t.trim().to_string())
        };
        let refs = |name: &str| -> Result<Vec<i64>, IoError> {
            node.children()
                .filter(|c| c.has_tag_name(name))
                .map(|c| cx.id(c, "ref"))
                .collect()
        };
        let adjacent = |name: &str| -> Result<(Option<i64>, bool), IoError> {
            match cx.child(node, name) {
                Some(a) => {
                    let r = cx.id(a, "ref")?;
                    // The format knows two directions: any other word (`Same`, a typo) was
                    // read as "opposite", and the neighbour dropped from the lane graph
                    // without a word.
                    let same = match a.attribute("drivingDir").map(str::trim) {
                        None | Some("same") => true,
                        Some("opposite") => false,
                        Some(other) => {
                            return Err(cx.err(
                                a,
                                format!(
                                    "drivingDir=\"{}\" is not a direction of CommonRoad's: \
                                     same or opposite",
                                    crate::io::name::shown(other)
                                ),
                            ))
                        }
                    };
                    Ok((same.then_some(r), true))
                }
                None => Ok((None, false)),
            }
        };
        let (left_same, has_left) = adjacent("adjacentLeft")?;
        let (right_same, has_right) = adjacent("adjacentRight")?;
        let (kind, crosswalk) = cx
            .child(node, "laneletType")
            .and_then(|t| t.text())
            .map(|t| lane_type(t.trim()))
            .unwrap_or((LaneType::SurfaceStreet, false));
        let mut speed_limit = match cx.child(node, "speedLimit") {
            Some(s) => Some(cx.number(s)?),
            None => None,
        };
        for r in refs("trafficSignRef")? {
            if let Some(v) = speed_signs.get(&r) {
                speed_limit = Some(*v);
            }
        }
        if let Some(stop) = cx.child(node, "stopLine") {
            let mut pts = cx.points(stop)?;
            if pts.len() < 2 {
                pts = vec![left.last(), right.last()];
            }
            parts.stop_lines.push(StopLine {
                points: pts,
                lanes: vec![id],
            });
        }
        if crosswalk {
            let ring = right
                .points()
                .iter()
                .chain(left.points().iter().rev())
                .copied();
            parts
                .crosswalks
                .push(Polygon::new(ring).map_err(|e| cx.err(node, e.to_string()))?);
            continue;
        }
        let (mut left_marking, mut right_marking) = (marking(lb), marking(rb));
        let (width, side) = crate::scene::signed_width(&left, &right);
        if width < crate::scene::ZERO_WIDTH {
            notes.zero_width.push(id);
        } else if side < -0.5 {
            notes.swapped.push(id);
            std::mem::swap(&mut left, &mut right);
            std::mem::swap(&mut left_marking, &mut right_marking);
        }
        let (successors, predecessors) = (refs("successor")?, refs("predecessor")?);
        if successors
            .iter()
            .chain(&predecessors)
            .chain(&left_same)
            .chain(&right_same)
            .any(|r| *r == id)
        {
            notes.own_link.push(id);
        }
        let mut lane = Lane::new(id, centerline(&left, &right));
        lane.left_boundary = Some(left.clone());
        lane.right_boundary = Some(right.clone());
        lane.lane_type = kind;
        lane.speed_limit = speed_limit;
        lane.is_intersection = intersection_lanes.contains(&id);
        lane.predecessors = predecessors;
        lane.successors = successors;
        lane.left_neighbors = left_same.into_iter().collect();
        lane.right_neighbors = right_same.into_iter().collect();
        parts.lanes.push(lane);
        raws.push(RawLanelet {
            id,
            left_marking,
            right_marking,
            left,
            right,
            has_left,
            has_right,
            kind,
            crosswalk,
        });
    }

    let surfaces: Vec<(i64, Polygon)> = parts
        .lanes
        .iter()
        .filter_map(|l| Some((l.id, l.surface()?)))
        .collect();
    let grid = Surfaces::new(&surfaces);
    for raw in &raws {
        // Oriented with the road on the left: the right bound as is, the left bound reversed.
        if !raw.has_right {
            push_edge_runs(&mut parts.road_edges, &raw.right, raw.id, &grid);
        }
        if !raw.has_left {
            push_edge_runs(&mut parts.road_edges, &raw.left.reversed(), raw.id, &grid);
        }
    }
    let mut line_ends = super::RoadLineEnds::of(&parts.road_lines);
    for raw in &raws {
        for (line, marking) in [
            (&raw.left, &raw.left_marking),
            (&raw.right, &raw.right_marking),
        ] {
            let Some(m) = marking else { continue };
            let kind = match m.as_str() {
                "dashed" | "broad_dashed" => RoadLineKind::Broken,
                "solid" | "broad_solid" => RoadLineKind::Solid,
                "no_marking" => continue,
                _ => RoadLineKind::Unknown,
            };
            super::push_unique_road_line(
                &mut parts.road_lines,
                &mut line_ends,
                RoadLine {
                    kind,
                    yellow: false,
                    line: line.clone(),
                },
            );
        }
    }
    // By id through a map: a search of the list per lanelet was quadratic in their number.
    let by_id: HashMap<i64, &Polygon> = surfaces.iter().map(|(id, p)| (*id, p)).collect();
    parts.drivable_areas = raws
        .iter()
        .filter(|r| !r.crosswalk && r.kind != LaneType::Other)
        .filter_map(|r| by_id.get(&r.id).map(|p| (*p).clone()))
        .collect();
    notes.far = crate::scene::far_links(&parts.lanes);
    Map::new(parts).map_err(|e| IoError::Scene {
        path: cx.path.display().to_string(),
        location: "lanelet network".into(),
        error: e,
    })
}

/// Adds the parts of a candidate edge (road on its left) that do not run inside another
/// lanelet: probing just outside each segment tells a real edge from a bound that borders
/// another lanelet without being declared adjacent (common in intersections and merges).
fn push_edge_runs(out: &mut Vec<RoadEdge>, line: &Polyline, own: i64, surfaces: &Surfaces) {
    let pts = line.points();
    let mut run: Vec<Point> = Vec::new();
    let flush = |run: &mut Vec<Point>, out: &mut Vec<RoadEdge>| {
        if run.len() >= 2 {
            if let Ok(l) = Polyline::new(run.drain(..)) {
                out.push(RoadEdge::new(RoadEdgeKind::Boundary, l));
            }
        }
        run.clear();
    };
    for w in pts.windows(2) {
        let dir = (w[1] - w[0]).normalize();
        let probe = (w[0] + w[1]) * 0.5 + Point::new(dir.y, -dir.x) * 0.3;
        let interior = surfaces.any_contains(&probe, own);
        if interior {
            flush(&mut run, out);
        } else {
            if run.is_empty() {
                run.push(w[0]);
            }
            run.push(w[1]);
        }
    }
    flush(&mut run, out);
}

/// Side of the cells that list lanelet surfaces for [`push_edge_runs`], metres: a few lanelets
/// wide. Trying every surface for every probe made a map of 30,000 lanelets (a 7 MB file) take
/// 20 s, and one at the size limit half an hour.
const SURFACE_CELL: f64 = 16.0;
/// Most cells a surface is listed in; larger ones are tried for every probe.
const SURFACE_MAX_CELLS: i64 = 256;

/// Lanelet surfaces by the cells they cover ([`SURFACE_CELL`]).
struct Surfaces<'a> {
    all: &'a [(i64, Polygon)],
    index: CellIndex,
}

impl<'a> Surfaces<'a> {
    fn new(all: &'a [(i64, Polygon)]) -> Self {
        let mut index = CellIndex::new(SURFACE_CELL, SURFACE_MAX_CELLS);
        for (k, (_, poly)) in all.iter().enumerate() {
            let (lo, hi) = poly.bounds();
            index.insert(k, lo, hi);
        }
        Self { all, index }
    }

    /// Whether `p` lies inside a surface of a lanelet other than `own`.
    fn any_contains(&self, p: &Point, own: i64) -> bool {
        self.index.at(*p).any(|k| {
            let (id, poly) = &self.all[k];
            *id != own && poly.contains(p)
        })
    }
}

/// What the scene model leaves out or folds together, said once per scene: traffic lights
/// (their states are not modelled) and the kinds of vehicle read as `vehicle`.
fn warnings(root: Node) -> Vec<String> {
    let mut out = Vec::new();
    let lights = root
        .descendants()
        .filter(|n| n.has_tag_name("trafficLight"))
        .count();
    if lights > 0 {
        out.push(format!(
            "{lights} traffic light{} not read: signal states are not part of the scene model, so no agent is held at a red light",
            if lights == 1 { "" } else { "s" }
        ));
    }
    let mut kinds: std::collections::BTreeMap<&str, usize> = Default::default();
    for n in root.children().filter(|n| {
        matches!(
            n.tag_name().name(),
            "dynamicObstacle" | "staticObstacle" | "obstacle"
        )
    }) {
        let t = n
            .children()
            .find(|c| c.has_tag_name("type"))
            .and_then(|t| t.text())
            .unwrap_or("")
            .trim();
        if matches!(
            t,
            "truck" | "bus" | "motorcycle" | "priorityVehicle" | "taxi"
        ) {
            *kinds.entry(t).or_default() += 1;
        }
    }
    if !kinds.is_empty() {
        let list: Vec<String> = kinds.iter().map(|(k, n)| format!("{n} {k}")).collect();
        out.push(format!(
            "{} read as vehicles: a model that reads agents' sizes tells them apart by their length and width, the NGSIM checkpoint moves them as cars",
            list.join(", ")
        ));
    }
    out
}

fn agent_type(name: &str) -> AgentType {
    match name {
        "car" | "truck" | "bus" | "motorcycle" | "priorityVehicle" | "parkedVehicle" | "taxi" => {
            AgentType::Vehicle
        }
        "bicycle" => AgentType::Cyclist,
        "pedestrian" => AgentType::Pedestrian,
        _ => AgentType::Other,
    }
}

fn read_state(cx: &Ctx, node: Node) -> Result<(i64, AgentState), IoError> {
    let pos = cx.need(node, "position")?;
    let p = match cx.child(pos, "point") {
        Some(p) => cx.point(p)?,
        None => {
            // Uncertain positions come as shapes; their centre is the best estimate.
            let center = pos
                .descendants()
                .find(|c| c.has_tag_name("center"))
                .ok_or_else(|| cx.err(pos, "expected <point> or a shape with <center>"))?;
            cx.point(center)?
        }
    };
    let heading = cx.value(cx.need(node, "orientation")?)?;
    let time_node = cx.need(node, "time")?;
    // The middle of an interval is a step nobody wrote: [0, 4] put the state at step 2
    // without a word, and [0, 5] was refused as "time 2.5".
    if cx.child(time_node, "exact").is_none() {
        return Err(cx.err(
            time_node,
            "is not <exact>: an obstacle's state is at one time step, and an interval names \
             many",
        ));
    }
    let time = cx.value(time_node)?;
    if time < 0.0 || time.fract() != 0.0 {
        return Err(cx.err(
            node,
            format!("time {time} is not a non-negative step index"),
        ));
    }
    if time >= super::MAX_STEPS as f64 {
        return Err(cx.err(
            node,
            format!(
                "time step {time} is implausible (limit {})",
                super::MAX_STEPS
            ),
        ));
    }
    let v = match cx.child(node, "velocity") {
        Some(v) => cx.value(v)?,
        None => 0.0,
    };
    Ok((
        time as i64,
        AgentState {
            x: p.x,
            y: p.y,
            heading,
            vx: v * heading.cos(),
            vy: v * heading.sin(),
            valid: true,
        },
    ))
}

fn read_agents(cx: &Ctx, root: Node) -> Result<(Vec<Agent>, usize), IoError> {
    struct Raw {
        id: i64,
        kind: AgentType,
        length: f64,
        width: f64,
        states: Vec<(i64, AgentState)>,
        is_static: bool,
    }
    let mut raws = Vec::new();
    for node in root.children() {
        let is_static = match node.tag_name().name() {
            "dynamicObstacle" => false,
            "staticObstacle" => true,
            "obstacle" => {
                let role = cx.child(node, "role").and_then(|r| r.text()).unwrap_or("");
                role.trim() == "static"
            }
            _ => continue,
        };
        let id = cx.id(node, "id")?;
        let kind = agent_type(cx.need(node, "type")?.text().unwrap_or("").trim());
        let shape = cx.need(node, "shape")?;
        let (length, width) = if let Some(r) = cx.child(shape, "rectangle") {
            (
                cx.number(cx.need(r, "length")?)?,
                cx.number(cx.need(r, "width")?)?,
            )
        } else if let Some(c) = cx.child(shape, "circle") {
            let r = cx.number(cx.need(c, "radius")?)?;
            (2.0 * r, 2.0 * r)
        } else if let Some(p) = cx.child(shape, "polygon") {
            let pts = cx.points(p)?;
            let (lo, hi) = crate::geom::Polyline::new(pts)
                .map_err(|e| cx.err(p, e.to_string()))?
                .bounds();
            (hi.x - lo.x, hi.y - lo.y)
        } else {
            return Err(cx.err(shape, "expected <rectangle>, <circle> or <polygon>"));
        };
        let mut states = vec![read_state(cx, cx.need(node, "initialState")?)?];
        if let Some(traj) = cx.child(node, "trajectory") {
            for s in traj.children().filter(|c| c.has_tag_name("state")) {
                let (t, state) = read_state(cx, s)?;
                // A CommonRoad trajectory is a state per consecutive step: a time given twice
                // would overwrite a state unseen, one far ahead stretch the scene.
                let last = states.last().expect("the initial state").0;
                if t != last + 1 {
                    return Err(cx.err(
                        s,
                        format!(
                            "time {t} does not follow the previous state's time {last} (a trajectory has one state per step)"
                        ),
                    ));
                }
                states.push((t, state));
            }
        }
        // A static obstacle stays where its initial state puts it: one whose trajectory moves
        // (a role or tag mislabelled) had that motion dropped without a word.
        if is_static {
            let (_, first) = states[0];
            if let Some((t, s)) = states
                .iter()
                .find(|(_, s)| (s.x - first.x).hypot(s.y - first.y) > 0.01)
            {
                return Err(cx.err(
                    node,
                    format!(
                        "a static obstacle, but its trajectory moves it {:.2} m by time {t}: a \
                         static obstacle stays at its initial state; make it dynamic (a \
                         <dynamicObstacle>, or <role>dynamic</role>) to keep its motion",
                        (s.x - first.x).hypot(s.y - first.y)
                    ),
                ));
            }
        }
        raws.push(Raw {
            id,
            kind,
            length,
            width,
            states,
            is_static,
        });
    }
    let steps = raws
        .iter()
        .flat_map(|r| r.states.iter().map(|(t, _)| *t))
        .max()
        .map_or(0, |t| t as usize + 1);
    super::check_states(cx.path, "obstacles", raws.len(), steps)?;
    let agents = raws
        .into_iter()
        .map(|r| {
            let mut states = vec![AgentState::INVALID; steps];
            for (t, s) in &r.states {
                states[*t as usize] = *s;
            }
            if r.is_static {
                let s = r.states[0].1;
                states.fill(s);
            }
            Agent {
                id: r.id,
                agent_type: r.kind,
                length: r.length,
                width: r.width,
                states,
                is_static: r.is_static,
            }
        })
        .collect();
    Ok((agents, steps))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_static_obstacle_whose_trajectory_moves_is_refused_not_pinned() {
        let path = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("data/samples/commonroad/USA_US101-3_3_T-1.xml");
        let text = std::fs::read_to_string(&path).unwrap();
        let moving = text.replacen("<role>dynamic</role>", "<role>static</role>", 1);
        let e = parse(Path::new("s.xml"), &moving, &LoadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("<obstacle id=363>: a static obstacle, but its trajectory moves it"),
            "{e}"
        );
        // One that stays put is read, at its initial state throughout.
        let start = text.find("<obstacle id=\"363\">").unwrap();
        let end = start + text[start..].find("</obstacle>").unwrap();
        let obstacle = &text[start..end];
        let t0 = obstacle.find("<trajectory>").unwrap();
        let t1 = obstacle.find("</trajectory>").unwrap() + "</trajectory>".len();
        let still = text.replacen(
            obstacle,
            &obstacle
                .replacen("<role>dynamic</role>", "<role>static</role>", 1)
                .replacen(&obstacle[t0..t1], "", 1),
            1,
        );
        let scene = parse(Path::new("s.xml"), &still, &LoadOptions::default()).unwrap();
        let a = scene.agents.iter().find(|a| a.id == 363).unwrap();
        assert!(a.is_static && a.states.iter().all(|s| s.valid && s.x == a.states[0].x));
        // A state's time as an interval is refused, not read as its middle.
        let interval = text.replacen(
            "<exact>0</exact>\n      </time>",
            "<intervalStart>0</intervalStart><intervalEnd>4</intervalEnd>\n      </time>",
            1,
        );
        let e = parse(Path::new("s.xml"), &interval, &LoadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(e.contains("<time>: is not <exact>"), "{e}");
    }

    #[test]
    fn nesting_depth_is_checked_before_parsing() {
        assert_eq!(
            too_deep("<a><b/><c x='>'><!-- <d> --><![CDATA[<e>]]></c></a>", 2),
            None
        );
        assert_eq!(
            too_deep("<?xml version=\"1.0\"?><a><b><c/></b></a>", 2),
            None
        );
        assert_eq!(too_deep("<a>\n<b>\n<c></c></b></a>", 2), Some(8));
        let deep = format!(
            "<commonRoad>{}{}</commonRoad>",
            "<a>".repeat(200_000),
            "</a>".repeat(200_000)
        );
        let e = parse(Path::new("deep.xml"), &deep, &LoadOptions::default())
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("deep.xml: line 1: elements nested more than 256 deep"),
            "{e}"
        );
    }
}
