//! SVG output.

use std::fmt::Write;

use super::draw::{draw_scene, View};
use super::{Canvas, RenderError, RenderOptions, Rgba};
use crate::geom::Point;
use crate::scene::Scene;

struct SvgCanvas {
    body: String,
}

fn coords(pts: &[Point]) -> String {
    let mut s = String::with_capacity(pts.len() * 14);
    for p in pts {
        let _ = write!(s, "{:.1},{:.1} ", p.x, p.y);
    }
    s.pop();
    s
}

fn escape(t: &str) -> String {
    t.replace('&', "&amp;")
        .replace('<', "&lt;")
        .replace('>', "&gt;")
}

impl Canvas for SvgCanvas {
    fn fill_polygon(&mut self, pts: &[Point], c: Rgba) {
        let _ = writeln!(
            self.body,
            r#"<polygon points="{}" fill="{}" fill-opacity="{:.2}"/>"#,
            coords(pts),
            c.hex(),
            c.opacity()
        );
    }

    fn stroke(&mut self, pts: &[Point], width: f32, c: Rgba, dash: Option<[f32; 2]>, closed: bool) {
        let tag = if closed { "polygon" } else { "polyline" };
        let dash = dash
            .map(|[a, b]| format!(r#" stroke-dasharray="{a:.1} {b:.1}""#))
            .unwrap_or_default();
        let _ = writeln!(
            self.body,
            r#"<{tag} points="{}" fill="none" stroke="{}" stroke-opacity="{:.2}" stroke-width="{width:.2}" stroke-linejoin="round" stroke-linecap="round"{dash}/>"#,
            coords(pts),
            c.hex(),
            c.opacity()
        );
    }

    fn label(&mut self, at: Point, text: &str, size: f32, c: Rgba) {
        let [lo, hi] = self.label_box(at, text, size);
        let _ = writeln!(
            self.body,
            r#"<rect x="{:.1}" y="{:.1}" width="{:.1}" height="{:.1}" fill="white" fill-opacity="0.75"/><text x="{:.1}" y="{:.1}" font-family="monospace" font-size="{size:.1}" fill="{}">{}</text>"#,
            lo.x,
            lo.y,
            hi.x - lo.x,
            hi.y - lo.y,
            at.x,
            at.y + size as f64 * 0.9,
            c.hex(),
            escape(text)
        );
    }

    fn label_box(&self, at: Point, text: &str, size: f32) -> [Point; 2] {
        // Monospace glyphs are about 0.62 em wide.
        let w = (text.chars().count() as f32 * size * 0.62 + 4.0) as f64;
        let lo = Point::new(at.x - 2.0, at.y - 1.0);
        [lo, lo + Point::new(w, size as f64 + 3.0)]
    }
}

/// The scene as an SVG document.
pub fn render_svg(scene: &Scene, opts: &RenderOptions) -> Result<String, RenderError> {
    let view = View::fit(scene, opts)?;
    let mut c = SvgCanvas {
        body: String::new(),
    };
    draw_scene(&mut c, scene, &view, opts);
    Ok(format!(
        r#"<svg xmlns="http://www.w3.org/2000/svg" width="{w}" height="{h}" viewBox="0 0 {w} {h}">
<title>{}</title>
{}</svg>
"#,
        escape(&scene.meta.scenario_id),
        c.body,
        w = view.width,
        h = view.height
    ))
}
