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
    let role = |a: &crate::scene::Agent| {
        opts.roles
            .iter()
            .find(|(id, _)| *id == a.id)
            .map(|(_, r)| r.as_str())
    };
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
        let tl = corners
            .iter()
            .fold(Point::new(f64::INFINITY, f64::INFINITY), |m, p| m.inf(p));
        let tr_x = corners
            .iter()
            .map(|p| p.x)
            .fold(f64::NEG_INFINITY, f64::max);
        let (text, size) = match role(a) {
            Some(r) => (format!("{} {r}", a.id), 11.0),
            None => (a.id.to_string(), 9.0),
        };
        c.label(
            Point::new(tr_x + 2.0, tl.y - size),
            &text,
            size as f32,
            Rgba(15, 15, 15, 255),
        );
    }
}

/// Draws the whole scene at `step` (default: the current step).
pub fn draw_scene(c: &mut dyn Canvas, scene: &Scene, v: &View, opts: &RenderOptions) {
    draw_map(c, scene, v);
    let step = opts.step.unwrap_or(scene.meta.current_step);
    draw_agents(c, scene, v, step, opts);
    draw_caption(c, scene, v, step, opts);
}

pub(crate) fn draw_caption(
    c: &mut dyn Canvas,
    scene: &Scene,
    v: &View,
    step: usize,
    opts: &RenderOptions,
) {
    let text = opts.caption.clone().unwrap_or_else(|| {
        format!(
            "{}  t = {:.1} s  step {}/{}",
            scene.meta.scenario_id,
            (step as f64 - scene.meta.current_step as f64) * scene.meta.dt,
            step,
            scene.num_steps().saturating_sub(1)
        )
    });
    c.label(Point::new(6.0, 6.0), &text, 11.0, Rgba(10, 10, 10, 255));
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
    c.label(
        Point::new(12.0 + len, y - 6.0),
        "10 m",
        9.0,
        Rgba(10, 10, 10, 255),
    );
}
