//! The one drawing routine: map, trails, boxes and labels of a scene at one step.

use super::{Canvas, RenderError, RenderOptions, Rgba};
use crate::geom::Point;
use crate::scene::{AgentType, Scene};

const BACKGROUND: Rgba = Rgba(226, 228, 218, 255);
const ROAD: Rgba = Rgba(178, 180, 184, 255);
const LANE_CENTRE: Rgba = Rgba(250, 250, 250, 110);
const EDGE: Rgba = Rgba(40, 40, 40, 255);
const WHITE_LINE: Rgba = Rgba(255, 255, 255, 255);
const YELLOW_LINE: Rgba = Rgba(240, 190, 20, 255);
const CROSSWALK: Rgba = Rgba(255, 255, 255, 150);
const STOP: Rgba = Rgba(200, 30, 30, 255);
const BUMP: Rgba = Rgba(230, 140, 40, 160);
/// Agents a request names.
const HIGHLIGHT: Rgba = Rgba(210, 30, 60, 255);

fn agent_color(t: AgentType, ego: bool) -> Rgba {
    if ego {
        return Rgba(235, 110, 20, 255);
    }
    match t {
        AgentType::Vehicle => Rgba(40, 100, 200, 255),
        AgentType::Pedestrian => Rgba(30, 150, 60, 255),
        AgentType::Cyclist => Rgba(140, 60, 170, 255),
        AgentType::Other => Rgba(110, 110, 110, 255),
    }
}

/// The world window shown and its mapping to pixels (uniform scale, y up in the world).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct View {
    /// World coordinates of the top-left pixel.
    pub origin: Point,
    /// Pixels per metre.
    pub scale: f64,
    /// Image width, pixels.
    pub width: u32,
    /// Image height, pixels.
    pub height: u32,
}

impl View {
    /// Frames every valid agent position (or the whole map without agents) plus the margin.
    pub fn fit(scene: &Scene, opts: &RenderOptions) -> Result<Self, RenderError> {
        let pts = scene
            .agents
            .iter()
            .flat_map(|a| a.states.iter().filter(|s| s.valid).map(|s| s.position()));
        let bounds = pts.fold(None, |acc: Option<(Point, Point)>, p| {
            Some(acc.map_or((p, p), |(lo, hi)| (lo.inf(&p), hi.sup(&p))))
        });
        let (mut lo, mut hi) = bounds
            .or_else(|| scene.map.bounds())
            .ok_or_else(|| RenderError::Size("the scene has neither agents nor a map".into()))?;
        let m = Point::new(opts.margin, opts.margin);
        lo -= m;
        hi += m;
        if !(opts.width >= 64 && opts.width <= 8192) {
            return Err(RenderError::Size(format!(
                "width {} is outside 64..8192 pixels",
                opts.width
            )));
        }
        let w = opts.width as f64;
        let (ww, wh) = ((hi.x - lo.x).max(1.0), (hi.y - lo.y).max(1.0));
        // Keep pictures between 4:1 and 2:3 so that long highways and tall scenes stay legible.
        let aspect = (wh / ww).clamp(0.25, 1.5);
        let h = (w * aspect).round();
        let scale = (w / ww).min(h / wh);
        let centre = (lo + hi) * 0.5;
        let origin = Point::new(centre.x - 0.5 * w / scale, centre.y + 0.5 * h / scale);
        Ok(Self {
            origin,
            scale,
            width: opts.width,
            height: h as u32,
        })
    }

    /// World point → pixel.
    pub fn px(&self, p: Point) -> Point {
        Point::new(
            (p.x - self.origin.x) * self.scale,
            (self.origin.y - p.y) * self.scale,
        )
    }

    fn pxs(&self, pts: &[Point]) -> Vec<Point> {
        pts.iter().map(|p| self.px(*p)).collect()
    }

    fn visible(&self, (lo, hi): (Point, Point)) -> bool {
        let (a, b) = (
            self.px(Point::new(lo.x, hi.y)),
            self.px(Point::new(hi.x, lo.y)),
        );
        b.x >= 0.0 && a.x <= self.width as f64 && b.y >= 0.0 && a.y <= self.height as f64
    }
}

fn bounds(pts: &[Point]) -> (Point, Point) {
    pts.iter()
        .fold((pts[0], pts[0]), |(lo, hi), p| (lo.inf(p), hi.sup(p)))
}

/// The static part: background, road surface, markings, edges, crosswalks, stop lines.
pub(crate) fn draw_map(c: &mut dyn Canvas, scene: &Scene, v: &View) {
    let (w, h) = (v.width as f64, v.height as f64);
    c.fill_polygon(
        &[
            Point::new(0.0, 0.0),
            Point::new(w, 0.0),
            Point::new(w, h),
            Point::new(0.0, h),
        ],
        BACKGROUND,
    );
    let map = &scene.map;
    let metres = |m: f64| (m * v.scale) as f32;
    if map.drivable_areas().is_empty() {
        // Without road surfaces (WOMD), wide strokes along lane centres read as the road.
        for lane in map.lanes().iter().filter(|l| l.lane_type.is_vehicle_lane()) {
            let pts = lane.centerline.points();
            if v.visible(bounds(pts)) {
                c.stroke(&v.pxs(pts), metres(3.8), ROAD, None, false);
            }
        }
    }
    for a in map.drivable_areas() {
        if v.visible(a.bounds()) {
            c.fill_polygon(&v.pxs(a.points()), ROAD);
        }
    }
    for cw in map.crosswalks() {
        if v.visible(cw.bounds()) {
            c.fill_polygon(&v.pxs(cw.points()), CROSSWALK);
        }
    }
    for sb in map.speed_bumps() {
        if v.visible(sb.bounds()) {
            c.fill_polygon(&v.pxs(sb.points()), BUMP);
        }
    }
    for lane in map.lanes() {
        let pts = lane.centerline.points();
        if v.visible(bounds(pts)) {
            c.stroke(&v.pxs(pts), 1.0, LANE_CENTRE, Some([2.0, 4.0]), false);
        }
    }
    for l in map.road_lines() {
        let pts = l.line.points();
        if !v.visible(bounds(pts)) {
            continue;
        }
        let color = if l.yellow { YELLOW_LINE } else { WHITE_LINE };
        let dash = matches!(l.kind, crate::scene::RoadLineKind::Broken)
            .then(|| [metres(3.0).max(3.0), metres(6.0).max(4.0)]);
        let width = if matches!(l.kind, crate::scene::RoadLineKind::DoubleSolid) {
            2.5
        } else {
            1.5
        };
        c.stroke(&v.pxs(pts), width, color, dash, false);
    }
    for e in map.road_edges() {
        let pts = e.line().points();
        if v.visible(bounds(pts)) {
            c.stroke(&v.pxs(pts), 2.0, EDGE, None, false);
        }
    }
    for s in map.stop_lines() {
        let pts = v.pxs(&s.points);
        if pts.len() >= 2 {
            c.stroke(&pts, 3.0, STOP, None, false);
        } else if let Some(p) = pts.first() {
            let r = 4.0;
            let oct: Vec<Point> = (0..8)
                .map(|k| {
                    let a = std::f64::consts::PI / 8.0 + k as f64 * std::f64::consts::PI / 4.0;
                    p + Point::new(r * a.cos(), r * a.sin())
                })
                .collect();
            c.fill_polygon(&oct, STOP);
        }
    }
}

/// Trails, boxes and labels of the agents at `step`.
pub(crate) fn draw_agents(
    c: &mut dyn Canvas,
    scene: &Scene,
    v: &View,
    step: usize,
    opts: &RenderOptions,
) {
    let current = scene.meta.current_step;
    let runs = |a: &crate::scene::Agent, from: usize, to: usize| -> Vec<Vec<Point>> {
        // Split at invalid steps so that a gap is not drawn as a straight jump.
        let mut out = vec![];
        let mut run = vec![];
        for s in a.states.iter().take(to + 1).skip(from) {
            if s.valid {
                run.push(v.px(s.position()));
            } else if !run.is_empty() {
                out.push(std::mem::take(&mut run));
            }
        }
        out.push(run);
        out.into_iter().filter(|r| r.len() >= 2).collect()
    };
    let role = |a: &crate::scene::Agent| opts.role(a.id);
    let colour = |a: &crate::scene::Agent| match role(a) {
        Some(_) => HIGHLIGHT,
        None => agent_color(a.agent_type, scene.meta.ego == Some(a.id)),
    };
    // Highlighted agents last, so that their trails lie on top.
    let mut order: Vec<&crate::scene::Agent> = scene.agents.iter().collect();
    order.sort_by_key(|a| role(a).is_some());
    for &a in &order {
        let mut col = colour(a);
        let width = if role(a).is_some() { 3.0 } else { 2.0 };
        // Solid up to the drawn step (the motion so far, simulated or recorded), dashed after
        // it (the future from the current step on when the current step is drawn).
        if opts.history {
            col.3 = 200;
            for r in runs(a, 0, step) {
                c.stroke(&r, width, col, None, false);
            }
        }
        if opts.future && step < a.states.len() {
            col.3 = 160;
            for r in runs(a, step.max(current), a.states.len() - 1) {
                c.stroke(&r, width - 0.5, col, Some([5.0, 4.0]), false);
            }
        }
    }
    for &a in &order {
        let Some(b) = a.footprint(step) else { continue };
        let col = colour(a);
        let corners = v.pxs(&b.corners());
        c.fill_polygon(&corners, col);
        c.stroke(&corners, 1.0, Rgba(20, 20, 20, 255), None, true);
        // A light bar across the front tells which way the agent faces.
        let (u, _) = b.axes();
        let front = b.center + u * (0.5 * b.length);
        let back = front - u * (0.25 * b.length.min(2.0));
        let cs = b.corners();
        let bar = [
            v.px(back + (cs[1] - front) * 0.8),
            v.px(back + (cs[2] - front) * 0.8),
            v.px(front + (cs[2] - front) * 0.8),
            v.px(front + (cs[1] - front) * 0.8),
        ];
        c.fill_polygon(&bar, Rgba(255, 255, 255, 170));
    }
}

/// Draws the whole scene at `step` (default: the current step).
pub fn draw_scene(c: &mut dyn Canvas, scene: &Scene, v: &View, opts: &RenderOptions) {
    draw_map(c, scene, v);
    let step = opts.step.unwrap_or(scene.meta.current_step);
    draw_agents(c, scene, v, step, opts);
    let legend = legend_rect(c, scene, v, opts);
    draw_overlay(c, scene, v, step, opts, legend);
}

/// A rectangle in pixels: top-left and bottom-right.
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Rect {
    pub(crate) lo: Point,
    pub(crate) hi: Point,
}

impl Rect {
    fn of(pts: &[Point]) -> Self {
        let (lo, hi) = bounds(pts);
        Self { lo, hi }
    }

    fn overlap(&self, o: &Rect) -> f64 {
        let w = self.hi.x.min(o.hi.x) - self.lo.x.max(o.lo.x);
        let h = self.hi.y.min(o.hi.y) - self.lo.y.max(o.lo.y);
        if w > 0.0 && h > 0.0 {
            w * h
        } else {
            0.0
        }
    }

    fn inside(&self, v: &View) -> bool {
        self.lo.x >= 0.0
            && self.lo.y >= 0.0
            && self.hi.x <= v.width as f64
            && self.hi.y <= v.height as f64
    }
}

/// Rectangles (boxes, caption, legend, labels placed) by the cells of a grid over the picture
/// that they touch, so that a label is checked only against those near it: checked against
/// all of them, placing the labels took time growing with the square of the agents (a scene of
/// 4,000 vehicles sampled in 3 minutes, most of them placing labels in its GIF's frames, and
/// one of 20,000 did not finish). Only a rectangle inside the picture is ever chosen, so what
/// lies outside it is kept in the border cells, clamped.
struct RectGrid {
    rects: Vec<Rect>,
    cells: Vec<Vec<usize>>,
    cols: usize,
    rows: usize,
}

impl RectGrid {
    /// Pixels a cell is wide and high: a few labels across.
    const CELL: f64 = 16.0;

    fn new(v: &View) -> Self {
        let cols = (v.width as f64 / Self::CELL).ceil() as usize + 1;
        let rows = (v.height as f64 / Self::CELL).ceil() as usize + 1;
        Self {
            rects: Vec::new(),
            cells: vec![Vec::new(); cols * rows],
            cols,
            rows,
        }
    }

    /// The cells `r` touches (columns, rows), clamped to the grid.
    fn span(&self, r: &Rect) -> (std::ops::Range<usize>, std::ops::Range<usize>) {
        let at = |x: f64, n: usize| (x / Self::CELL).floor().clamp(0.0, (n - 1) as f64) as usize;
        (
            at(r.lo.x, self.cols)..at(r.hi.x, self.cols) + 1,
            at(r.lo.y, self.rows)..at(r.hi.y, self.rows) + 1,
        )
    }

    fn push(&mut self, r: Rect) {
        let k = self.rects.len();
        let (xs, ys) = self.span(&r);
        for y in ys {
            for x in xs.clone() {
                self.cells[y * self.cols + x].push(k);
            }
        }
        self.rects.push(r);
    }

    /// Whether any of the rectangles overlaps `r`.
    fn any_over(&self, r: &Rect) -> bool {
        let (xs, ys) = self.span(r);
        ys.into_iter().any(|y| {
            xs.clone().any(|x| {
                self.cells[y * self.cols + x]
                    .iter()
                    .any(|&k| self.rects[k].overlap(r) > 0.0)
            })
        })
    }

    /// The area of `r` the rectangles cover, each counted once.
    fn overlap(&self, r: &Rect) -> f64 {
        let (xs, ys) = self.span(r);
        let mut seen: Vec<usize> = Vec::new();
        for y in ys {
            for x in xs.clone() {
                seen.extend(&self.cells[y * self.cols + x]);
            }
        }
        seen.sort_unstable();
        seen.dedup();
        seen.iter().map(|&k| self.rects[k].overlap(r)).sum()
    }
}

/// A label to place beside a box: what it says, how big, and whether it must be shown.
pub(crate) struct LabelRequest {
    pub(crate) text: String,
    pub(crate) size: f32,
    pub(crate) target: Rect,
    pub(crate) named: bool,
}

/// Places labels beside their boxes, clear of every obstacle (boxes, caption, legend) and of
/// each other: the first clear spot of eight around the box, then the same farther out. A
/// label with no clear spot is left out, unless it names an agent of the request, which takes
/// its least covered spot. Returns where each label's `at` goes.
pub(crate) fn place_labels(
    c: &dyn Canvas,
    v: &View,
    requests: &[LabelRequest],
    obstacles: &[Rect],
) -> Vec<Option<Point>> {
    let mut near = RectGrid::new(v);
    for o in obstacles {
        near.push(*o);
    }
    let mut out = vec![None; requests.len()];
    // Named agents choose first.
    let mut order: Vec<usize> = (0..requests.len()).collect();
    order.sort_by_key(|&i| !requests[i].named);
    for i in order {
        let r = &requests[i];
        let [l0, l1] = c.label_box(Point::new(0.0, 0.0), &r.text, r.size);
        let (w, h) = (l1.x - l0.x, l1.y - l0.y);
        let (lo, hi) = (r.target.lo, r.target.hi);
        let (cx, cy) = (0.5 * (lo.x + hi.x), 0.5 * (lo.y + hi.y));
        let mut spots = Vec::with_capacity(16);
        for gap in [2.0, 2.0 + h] {
            spots.extend([
                Point::new(hi.x + gap, lo.y - h),
                Point::new(hi.x + gap, hi.y),
                Point::new(lo.x - w - gap, lo.y - h),
                Point::new(lo.x - w - gap, hi.y),
                Point::new(cx - 0.5 * w, lo.y - h - gap),
                Point::new(cx - 0.5 * w, hi.y + gap),
                Point::new(hi.x + gap, cy - 0.5 * h),
                Point::new(lo.x - w - gap, cy - 0.5 * h),
            ]);
        }
        let covered = |tl: Point| {
            let rect = Rect {
                lo: tl,
                hi: tl + Point::new(w, h),
            };
            let area = near.overlap(&rect);
            (rect, area)
        };
        // Whether a spot is clear is settled at the first rectangle over it: in a crowd, at
        // once.
        let clear = spots
            .iter()
            .map(|&p| Rect {
                lo: p,
                hi: p + Point::new(w, h),
            })
            .find(|rect| rect.inside(v) && !near.any_over(rect));
        let chosen = match clear {
            Some(rect) => Some(rect),
            None if r.named => spots
                .iter()
                .map(|&p| covered(p))
                .filter(|(rect, _)| rect.inside(v))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .map(|(rect, _)| rect),
            None => None,
        };
        if let Some(rect) = chosen {
            near.push(rect);
            // `at` is the label's anchor; its box starts at `l0` from it.
            out[i] = Some(rect.lo - l0);
        }
    }
    out
}

/// One legend row: a swatch (a box in a colour, or a solid or dashed line) and its meaning.
enum Swatch {
    Box(Rgba),
    Line { dashed: bool },
}

/// The legend's rows for this scene and these options: only what the picture shows.
fn legend_rows(scene: &Scene, opts: &RenderOptions) -> Vec<(Swatch, &'static str)> {
    let mut rows = Vec::new();
    if opts.history {
        rows.push((Swatch::Line { dashed: false }, "motion so far"));
    }
    if opts.future {
        rows.push((Swatch::Line { dashed: true }, "future"));
    }
    let has = |t: AgentType| {
        scene
            .agents
            .iter()
            .any(|a| a.agent_type == t && scene.meta.ego != Some(a.id))
    };
    for (t, name) in [
        (AgentType::Vehicle, "vehicle"),
        (AgentType::Pedestrian, "pedestrian"),
        (AgentType::Cyclist, "cyclist"),
        (AgentType::Other, "other"),
    ] {
        if has(t) {
            rows.push((Swatch::Box(agent_color(t, false)), name));
        }
    }
    if scene.meta.ego.is_some() {
        rows.push((Swatch::Box(agent_color(AgentType::Vehicle, true)), "ego"));
    }
    if !opts.roles.is_empty() {
        rows.push((Swatch::Box(HIGHLIGHT), "named in the request"));
    }
    rows
}

const LEGEND_TEXT: f32 = 9.0;

/// The legend's rectangle: in the right-hand corner (top or bottom) that the agents' paths
/// cross least, the same in every frame of an animation.
pub(crate) fn legend_rect(
    c: &dyn Canvas,
    scene: &Scene,
    v: &View,
    opts: &RenderOptions,
) -> Option<Rect> {
    let rows = legend_rows(scene, opts);
    if rows.is_empty() {
        return None;
    }
    let text_w = rows
        .iter()
        .map(|(_, t)| {
            let [lo, hi] = c.label_box(Point::new(0.0, 0.0), t, LEGEND_TEXT);
            hi.x - lo.x
        })
        .fold(0.0, f64::max);
    let (w, h) = (text_w + 26.0, rows.len() as f64 * 14.0 + 6.0);
    let (vw, vh) = (v.width as f64, v.height as f64);
    let at = |y: f64| Rect {
        lo: Point::new(vw - w - 6.0, y),
        hi: Point::new(vw - 6.0, y + h),
    };
    let candidates = [at(6.0), at(vh - h - 6.0)];
    let crossed = |r: &Rect| {
        scene
            .agents
            .iter()
            .flat_map(|a| a.states.iter().filter(|s| s.valid))
            .map(|s| v.px(s.position()))
            .filter(|p| p.x >= r.lo.x && p.x <= r.hi.x && p.y >= r.lo.y && p.y <= r.hi.y)
            .count()
    };
    candidates.into_iter().min_by_key(crossed)
}

fn draw_legend(c: &mut dyn Canvas, scene: &Scene, r: &Rect, opts: &RenderOptions) {
    let frame = [
        r.lo,
        Point::new(r.hi.x, r.lo.y),
        r.hi,
        Point::new(r.lo.x, r.hi.y),
    ];
    c.fill_polygon(&frame, Rgba(255, 255, 255, 215));
    c.stroke(&frame, 1.0, Rgba(90, 90, 90, 255), None, true);
    for (k, (swatch, text)) in legend_rows(scene, opts).iter().enumerate() {
        let y = r.lo.y + 5.0 + k as f64 * 14.0;
        let x = r.lo.x + 5.0;
        match swatch {
            Swatch::Box(col) => {
                let b = [
                    Point::new(x + 2.0, y + 1.0),
                    Point::new(x + 14.0, y + 1.0),
                    Point::new(x + 14.0, y + 9.0),
                    Point::new(x + 2.0, y + 9.0),
                ];
                c.fill_polygon(&b, *col);
                c.stroke(&b, 1.0, Rgba(20, 20, 20, 255), None, true);
            }
            Swatch::Line { dashed } => {
                let dash = dashed.then_some([4.0, 3.0]);
                c.stroke(
                    &[Point::new(x, y + 5.0), Point::new(x + 16.0, y + 5.0)],
                    2.0,
                    Rgba(40, 100, 200, 255),
                    dash,
                    false,
                );
            }
        }
        c.label(
            Point::new(x + 21.0, y + 1.0),
            text,
            LEGEND_TEXT,
            Rgba(15, 15, 15, 255),
        );
    }
}

/// Everything drawn over the agents at `step`: caption, scale bar, the legend (in `legend`,
/// from [`legend_rect`], found once for every frame of an animation), and the agents' labels,
/// placed clear of the boxes, of each other and of the rest.
pub(crate) fn draw_overlay(
    c: &mut dyn Canvas,
    scene: &Scene,
    v: &View,
    step: usize,
    opts: &RenderOptions,
    legend: Option<Rect>,
) {
    let mut obstacles = draw_caption(c, scene, v, step, opts);
    if let Some(r) = legend {
        draw_legend(c, scene, &r, opts);
        obstacles.push(r);
    }
    let role = |id| opts.role(id);
    let mut requests = Vec::new();
    for a in &scene.agents {
        let Some(b) = a.footprint(step) else { continue };
        let target = Rect::of(&v.pxs(&b.corners()));
        // One pixel of air around every box.
        obstacles.push(Rect {
            lo: target.lo - Point::new(1.0, 1.0),
            hi: target.hi + Point::new(1.0, 1.0),
        });
        let (text, size) = match role(a.id) {
            Some(r) => (format!("{} {r}", a.id), 11.0),
            None => (a.id.to_string(), 9.0),
        };
        requests.push(LabelRequest {
            text,
            size,
            target,
            named: role(a.id).is_some(),
        });
    }
    let spots = place_labels(c, v, &requests, &obstacles);
    for (r, at) in requests.iter().zip(spots) {
        if let Some(at) = at {
            c.label(at, &r.text, r.size, Rgba(15, 15, 15, 255));
        }
    }
}

/// The caption (top left) and a 10 m scale bar (bottom left); returns the rectangles they
/// cover.
fn draw_caption(
    c: &mut dyn Canvas,
    scene: &Scene,
    v: &View,
    step: usize,
    opts: &RenderOptions,
) -> Vec<Rect> {
    let text = opts.caption.clone().unwrap_or_else(|| {
        format!(
            "{}  t = {:.1} s  step {}/{}",
            scene.meta.scenario_id,
            (step as f64 - scene.meta.current_step as f64) * scene.meta.dt,
            step,
            scene.num_steps().saturating_sub(1)
        )
    });
    let at = Point::new(6.0, 6.0);
    c.label(at, &text, 11.0, Rgba(10, 10, 10, 255));
    let [lo, hi] = c.label_box(at, &text, 11.0);
    let mut covered = vec![Rect { lo, hi }];
    // A 10 m scale bar in the bottom-left corner.
    let y = v.height as f64 - 12.0;
    let len = 10.0 * v.scale;
    c.stroke(
        &[Point::new(8.0, y), Point::new(8.0 + len, y)],
        3.0,
        Rgba(10, 10, 10, 255),
        None,
        false,
    );
    let at = Point::new(12.0 + len, y - 6.0);
    c.label(at, "10 m", 9.0, Rgba(10, 10, 10, 255));
    let [_, hi] = c.label_box(at, "10 m", 9.0);
    covered.push(Rect {
        lo: Point::new(6.0, y - 8.0),
        hi,
    });
    covered
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};

    /// A canvas that keeps what was written and where (with the SVG canvas's text metrics).
    #[derive(Default)]
    struct Recorder {
        labels: Vec<(String, Rect)>,
    }

    impl Canvas for Recorder {
        fn fill_polygon(&mut self, _: &[Point], _: Rgba) {}
        fn stroke(&mut self, _: &[Point], _: f32, _: Rgba, _: Option<[f32; 2]>, _: bool) {}
        fn label(&mut self, at: Point, text: &str, size: f32, _: Rgba) {
            let [lo, hi] = self.label_box(at, text, size);
            self.labels.push((text.to_string(), Rect { lo, hi }));
        }
        fn label_box(&self, at: Point, text: &str, size: f32) -> [Point; 2] {
            let w = (text.chars().count() as f32 * size * 0.62 + 4.0) as f64;
            let lo = Point::new(at.x - 2.0, at.y - 1.0);
            [lo, lo + Point::new(w, size as f64 + 3.0)]
        }
    }

    fn sample(name: &str) -> Scene {
        let p = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("data/samples/commonroad")
            .join(name);
        load_scene(&p, 0, &LoadOptions::default()).unwrap()
    }

    #[test]
    fn a_role_for_an_absent_agent_or_given_twice_is_refused() {
        let scene = sample("USA_US101-3_3_T-1.xml");
        let with = |roles: &[(i64, &str)]| RenderOptions {
            roles: roles.iter().map(|(i, r)| (*i, r.to_string())).collect(),
            ..RenderOptions::default()
        };
        with(&[(401, "cutter"), (399, "victim")])
            .check_roles(&scene)
            .unwrap();
        let e = with(&[(401, "cutter"), (4010, "victim")])
            .check_roles(&scene)
            .unwrap_err()
            .to_string();
        assert!(
            e.starts_with("the role \"victim\" for agent 4010: the scene has no agent 4010"),
            "{e}"
        );
        assert!(e.contains("401"), "{e}");
        let e = with(&[(401, "cutter"), (401, "victim")])
            .check_roles(&scene)
            .unwrap_err()
            .to_string();
        assert!(
            e.contains("agent 401 already has the role \"cutter\""),
            "{e}"
        );
    }

    #[test]
    fn labels_keep_clear_of_boxes_and_of_each_other_and_the_legend_says_what_is_drawn() {
        let scene = sample("USA_US101-3_3_T-1.xml");
        for width in [1000, 400, 160] {
            let opts = RenderOptions {
                width,
                roles: vec![(401, "cutter".into()), (399, "victim".into())],
                ..RenderOptions::default()
            };
            let v = View::fit(&scene, &opts).unwrap();
            let mut c = Recorder::default();
            draw_scene(&mut c, &scene, &v, &opts);
            let step = scene.meta.current_step;
            let boxes: Vec<(i64, Rect)> = scene
                .agents
                .iter()
                .filter_map(|a| Some((a.id, Rect::of(&v.pxs(&a.footprint(step)?.corners())))))
                .collect();
            let ids: Vec<&(String, Rect)> = c
                .labels
                .iter()
                .filter(|(t, _)| {
                    let first = t.split(' ').next().and_then(|w| w.parse::<i64>().ok());
                    boxes.iter().any(|(id, _)| Some(*id) == first)
                })
                .collect();
            for (t, r) in &ids {
                // A named agent's label takes its least covered spot when no spot is clear,
                // as on a picture 160 pixels wide; the others are left out instead.
                if width < 400 && t.contains(' ') {
                    continue;
                }
                for (id, b) in &boxes {
                    assert_eq!(r.overlap(b), 0.0, "width {width}: label {t:?} on box {id}");
                }
                for (u, o) in &c.labels {
                    if u != t {
                        assert_eq!(r.overlap(o), 0.0, "width {width}: {t:?} on {u:?}");
                    }
                }
                assert!(r.inside(&v), "width {width}: {t:?} outside the picture");
            }
            for want in ["401 cutter", "399 victim"] {
                assert!(
                    ids.iter().any(|(t, _)| t == want),
                    "width {width}: {want} missing"
                );
            }
            if width == 1000 {
                // Every agent is labelled where there is room.
                assert_eq!(ids.len(), boxes.len(), "{:?}", ids);
            }
            let texts: Vec<&str> = c.labels.iter().map(|(t, _)| t.as_str()).collect();
            for row in ["motion so far", "future", "vehicle", "named in the request"] {
                assert!(texts.contains(&row), "width {width}: legend lacks {row}");
            }
            assert!(!texts.contains(&"pedestrian") && !texts.contains(&"ego"));
        }
    }

    #[test]
    fn the_legend_lists_only_what_is_drawn() {
        let scene = sample("USA_Lanker-1_1_T-1.xml");
        let opts = RenderOptions {
            history: false,
            ..RenderOptions::default()
        };
        let rows: Vec<&str> = legend_rows(&scene, &opts).iter().map(|r| r.1).collect();
        assert_eq!(rows, ["future", "vehicle"]);
    }
}
