//! Pictures of scenes: SVG, PNG and animated GIF, in pure Rust.
//!
//! One drawing routine ([`draw::draw_scene`]) paints onto a [`Canvas`]; the SVG writer and the
//! tiny-skia rasteriser are two canvases, and the GIF is raster frames of successive steps.

mod draw;
mod font;
mod format;
mod gif;
mod raster;
mod svg;

pub use self::gif::{render_gif, render_gif_with_progress, MAX_GIF_FRAMES};
pub use draw::View;
pub use format::PictureFormat;
pub use raster::render_png;
pub use svg::render_svg;

use crate::geom::Point;

/// Errors from rendering.
#[derive(Debug, thiserror::Error)]
pub enum RenderError {
    /// The picture would be empty or absurdly large.
    #[error("cannot render: {0}")]
    Size(String),
    /// A role names an agent the scene lacks, or an agent twice. The id is the number the
    /// value was read as, so the message says "agent" and "role" rather than echoing a value
    /// (`01=b` was echoed as `1=b`).
    #[error("the role {role:?} for agent {id}: {message}")]
    Role {
        /// The agent id.
        id: crate::scene::AgentId,
        /// The role it was given.
        role: String,
        /// What is wrong.
        message: String,
    },
    /// A step was asked of an animation, which draws them all: the GIF came out the same as
    /// without it (`render -o x.gif --step 3` wrote every frame without a word).
    #[error(
        "step {0}: a GIF draws every step of the scene; draw one step as PNG or SVG (--step N \
         -o NAME.png), or leave the step out for the animation"
    )]
    StepOfAnimation(usize),
    /// The encoder failed.
    #[error("{format} encoding failed: {message}")]
    Encode {
        /// PNG or GIF.
        format: &'static str,
        /// The encoder's message.
        message: String,
    },
}

/// What to draw and how big.
#[derive(Debug, Clone, PartialEq)]
pub struct RenderOptions {
    /// Image width in pixels (the height follows from the scene's extent).
    pub width: u32,
    /// Metres of map shown around the agents.
    pub margin: f64,
    /// The step whose boxes are drawn (default: the current step).
    pub step: Option<usize>,
    /// Draw history trails (steps up to the drawn one).
    pub history: bool,
    /// Draw future trails (steps after the current one).
    pub future: bool,
    /// Caption written in the top-left corner.
    pub caption: Option<String>,
    /// Agents to highlight, each labelled with its role (`389 cutter`): the agents a request
    /// names.
    pub roles: Vec<(crate::scene::AgentId, String)>,
}

impl Default for RenderOptions {
    fn default() -> Self {
        Self {
            width: 1000,
            margin: 15.0,
            step: None,
            history: true,
            future: true,
            caption: None,
            roles: Vec::new(),
        }
    }
}

impl RenderOptions {
    /// Every role names an agent of `scene`, once: a mistyped id would otherwise leave the
    /// picture without the highlight asked for, and say nothing.
    pub fn check_roles(&self, scene: &crate::scene::Scene) -> Result<(), RenderError> {
        for (i, (id, role)) in self.roles.iter().enumerate() {
            let err = |message: String| RenderError::Role {
                id: *id,
                role: role.clone(),
                message,
            };
            if let Some((_, first)) = self.roles[..i].iter().find(|(a, _)| a == id) {
                return Err(err(format!(
                    "agent {id} already has the role {first:?}; give each agent one role"
                )));
            }
            if !scene.agents.iter().any(|a| a.id == *id) {
                let ids: Vec<String> = scene.agents.iter().map(|a| a.id.to_string()).collect();
                let shown = if ids.len() > 20 {
                    format!("{}, … ({} in all)", ids[..20].join(", "), ids.len())
                } else {
                    ids.join(", ")
                };
                return Err(err(format!(
                    "the scene has no agent {id}; its agents: {shown}"
                )));
            }
        }
        Ok(())
    }

    /// The role `id` is labelled with, when the request names it.
    pub(crate) fn role(&self, id: crate::scene::AgentId) -> Option<&str> {
        self.roles
            .iter()
            .find(|(a, _)| *a == id)
            .map(|(_, r)| r.as_str())
    }
}

/// An RGBA colour.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Rgba(pub u8, pub u8, pub u8, pub u8);

impl Rgba {
    fn hex(self) -> String {
        format!("#{:02x}{:02x}{:02x}", self.0, self.1, self.2)
    }

    fn opacity(self) -> f32 {
        self.3 as f32 / 255.0
    }
}

/// A drawing surface in pixel coordinates (y down).
pub trait Canvas {
    /// Fills a closed polygon.
    fn fill_polygon(&mut self, pts: &[Point], color: Rgba);
    /// Strokes a polyline; `dash` is `[on, off]` in pixels.
    fn stroke(
        &mut self,
        pts: &[Point],
        width: f32,
        color: Rgba,
        dash: Option<[f32; 2]>,
        closed: bool,
    );
    /// Writes a short label with its top-left corner at `at`, `size` pixels tall, on a halo.
    fn label(&mut self, at: Point, text: &str, size: f32, color: Rgba);
    /// The pixels `label` covers (halo included), top-left and bottom-right: what label
    /// placement keeps clear of boxes and of other labels.
    fn label_box(&self, at: Point, text: &str, size: f32) -> [Point; 2];
}
