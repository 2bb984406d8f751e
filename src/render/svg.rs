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

/// Text as SVG character data: markup characters as entities, and control and invisible
/// characters (which XML 1.0 cannot hold at all, even as references, or which would reorder
/// the label) as visible escapes ([`crate::io::name::shown`]'s form).
fn escape(t: &str) -> String {
    let mut out = String::with_capacity(t.len());
    for c in t.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&apos;"),
            c if crate::io::name::unshowable(c) || matches!(c, '\u{FFFE}' | '\u{FFFF}') => {
                let _ = write!(out, "\\u{{{:04X}}}", c as u32);
            }
            c => out.push(c),
        }
    }
    out
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_svg_is_well_formed_whatever_the_text_it_writes() {
        let p =
            std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        let mut scene = crate::io::load_scene(&p, 0, &Default::default()).unwrap();
        // Readers refuse such ids; the SVG must not depend on that.
        scene.meta.scenario_id = "a\u{1b}]0;x\u{7}\n</title><script>&\"'\u{202E}\u{FFFF}".into();
        let svg = render_svg(&scene, &RenderOptions::default()).unwrap();
        let doc = roxmltree::Document::parse(&svg).expect("well-formed XML");
        let title = doc
            .descendants()
            .find(|n| n.has_tag_name("title"))
            .and_then(|n| n.text())
            .unwrap();
        assert_eq!(
            title,
            "a\\u{001B}]0;x\\u{0007}\\u{000A}</title><script>&\"'\\u{202E}\\u{FFFF}"
        );
        assert!(!svg.contains("<script>"));
    }
}
