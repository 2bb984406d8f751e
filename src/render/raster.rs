//! Raster output with tiny-skia: PNG, and the frames of GIFs.

use tiny_skia::{
    Color, FillRule, LineCap, LineJoin, Paint, PathBuilder, Pixmap, Stroke, StrokeDash, Transform,
};

use super::draw::{draw_scene, View};
use super::font::glyph;
use super::{Canvas, RenderError, RenderOptions, Rgba};
use crate::geom::Point;
use crate::scene::Scene;

pub(crate) struct RasterCanvas {
    pub(crate) pixmap: Pixmap,
}

impl RasterCanvas {
    pub(crate) fn new(v: &View) -> Result<Self, RenderError> {
        let pixmap = Pixmap::new(v.width, v.height)
            .ok_or_else(|| RenderError::Size(format!("{} x {} pixels", v.width, v.height)))?;
        Ok(Self { pixmap })
    }
}

fn paint(c: Rgba) -> Paint<'static> {
    let mut p = Paint::default();
    p.set_color(Color::from_rgba8(c.0, c.1, c.2, c.3));
    p.anti_alias = true;
    p
}

fn path(pts: &[Point], closed: bool) -> Option<tiny_skia::Path> {
    let mut pb = PathBuilder::new();
    let mut it = pts.iter().filter(|p| p.x.is_finite() && p.y.is_finite());
    let first = it.next()?;
    pb.move_to(first.x as f32, first.y as f32);
    for p in it {
        pb.line_to(p.x as f32, p.y as f32);
    }
    if closed {
        pb.close();
    }
    pb.finish()
}

impl Canvas for RasterCanvas {
    fn fill_polygon(&mut self, pts: &[Point], c: Rgba) {
        if let Some(p) = path(pts, true) {
            self.pixmap.fill_path(
                &p,
                &paint(c),
                FillRule::EvenOdd,
                Transform::identity(),
                None,
            );
        }
    }

    fn stroke(&mut self, pts: &[Point], width: f32, c: Rgba, dash: Option<[f32; 2]>, closed: bool) {
        let Some(p) = path(pts, closed) else { return };
        let stroke = Stroke {
            width: width.max(0.5),
            line_cap: LineCap::Round,
            line_join: LineJoin::Round,
            dash: dash.and_then(|[a, b]| StrokeDash::new(vec![a, b], 0.0)),
            ..Stroke::default()
        };
        self.pixmap
            .stroke_path(&p, &paint(c), &stroke, Transform::identity(), None);
    }

    fn label(&mut self, at: Point, text: &str, size: f32, c: Rgba) {
        let px = glyph_pixel(size);
        let (x0, y0) = (at.x as f32, at.y as f32);
        let [lo, hi] = self.label_box(at, text, size);
        if let Some(r) = tiny_skia::Rect::from_xywh(
            lo.x as f32,
            lo.y as f32,
            (hi.x - lo.x) as f32,
            (hi.y - lo.y) as f32,
        ) {
            self.pixmap.fill_rect(
                r,
                &paint(Rgba(255, 255, 255, 190)),
                Transform::identity(),
                None,
            );
        }
        let ink = paint(c);
        for (i, ch) in text.chars().enumerate() {
            let rows = glyph(ch);
            for (ry, bits) in rows.iter().enumerate() {
                for cx in 0..5 {
                    if bits & (1 << (4 - cx)) != 0 {
                        let x = x0 + (i as f32 * 6.0 + cx as f32) * px;
                        let y = y0 + ry as f32 * px;
                        if let Some(r) = tiny_skia::Rect::from_xywh(x, y, px, px) {
                            self.pixmap.fill_rect(r, &ink, Transform::identity(), None);
                        }
                    }
                }
            }
        }
    }

    fn label_box(&self, at: Point, text: &str, size: f32) -> [Point; 2] {
        // 5×7 glyphs on a 6-pixel pitch, scaled by whole pixels, on a one-pixel halo.
        let px = glyph_pixel(size) as f64;
        let w = text.chars().count() as f64 * 6.0 * px + 2.0 * px;
        let lo = Point::new(at.x - px, at.y - px);
        [lo, lo + Point::new(w, 9.0 * px)]
    }
}

/// The size of one font pixel for a label `size` pixels tall.
fn glyph_pixel(size: f32) -> f32 {
    (size / 7.0).round().max(1.0)
}

/// The scene as a PNG image.
pub fn render_png(scene: &Scene, opts: &RenderOptions) -> Result<Vec<u8>, RenderError> {
    let view = View::fit(scene, opts)?;
    let mut c = RasterCanvas::new(&view)?;
    draw_scene(&mut c, scene, &view, opts);
    c.pixmap.encode_png().map_err(|e| RenderError::Encode {
        format: "PNG",
        message: e.to_string(),
    })
}
