//! Animated GIFs of rollouts: one frame per step over a map drawn once.

use super::draw::{draw_agents, draw_map, draw_overlay, legend_rect, View};
use super::raster::RasterCanvas;
use super::{RenderError, RenderOptions};
use crate::scene::Scene;

/// Levels per channel of the fixed 6×7×6 colour cube (252 colours) plus 4 greys.
const R_LEVELS: u32 = 6;
const G_LEVELS: u32 = 7;
const B_LEVELS: u32 = 6;

fn palette() -> Vec<u8> {
    let mut p = Vec::with_capacity(256 * 3);
    for r in 0..R_LEVELS {
        for g in 0..G_LEVELS {
            for b in 0..B_LEVELS {
                p.push((r * 255 / (R_LEVELS - 1)) as u8);
                p.push((g * 255 / (G_LEVELS - 1)) as u8);
                p.push((b * 255 / (B_LEVELS - 1)) as u8);
            }
        }
    }
    for v in [60u8, 120, 180, 228] {
        p.extend_from_slice(&[v, v, v]);
    }
    p
}

/// Maps a pixel to the fixed palette: a fixed palette keeps colours stable across frames (no
/// flicker) and costs one lookup per pixel instead of a per-frame quantiser.
fn index(r: u8, g: u8, b: u8) -> u8 {
    let q = |v: u8, levels: u32| (v as u32 * (levels - 1) + 127) / 255;
    let (qr, qg, qb) = (q(r, R_LEVELS), q(g, G_LEVELS), q(b, B_LEVELS));
    let cube = (qr * G_LEVELS + qg) * B_LEVELS + qb;
    // Near-greys go to the closest of cube greys and the four extra greys.
    let (mx, mn) = (r.max(g).max(b), r.min(g).min(b));
    if mx - mn < 10 {
        let v = (r as u32 + g as u32 + b as u32) / 3;
        let extra = [60u32, 120, 180, 228];
        let (k, d) = extra
            .iter()
            .enumerate()
            .map(|(k, e)| (k, e.abs_diff(v)))
            .min_by_key(|(_, d)| *d)
            .expect("four greys");
        let cube_v = qr * 255 / (R_LEVELS - 1);
        if d < cube_v.abs_diff(v) {
            return (R_LEVELS * G_LEVELS * B_LEVELS) as u8 + k as u8;
        }
    }
    cube as u8
}

/// The most frames a GIF gets: 200 s at 10 Hz, twice the longest NGSIM scene here. A few KB
/// of scene with 100,000 steps rendered for minutes.
pub const MAX_GIF_FRAMES: usize = 2000;

/// The most pixels a GIF's frames may hold together: [`MAX_GIF_FRAMES`] frames at the default
/// width. Each limit alone let 2000 frames at `--width 8192` through: 41 took two minutes and
/// 26 MB, 2000 would take hours and more than a gigabyte.
pub const MAX_GIF_PIXELS: u64 = 3_000_000_000;

/// An animation of the scene's steps (trails grow as it plays), looping forever: every step,
/// or the last [`MAX_GIF_FRAMES`] of a longer scene (the motion before them drawn as trails).
/// `render` refuses such a scene instead of cutting it unasked.
pub fn render_gif(scene: &Scene, opts: &RenderOptions) -> Result<Vec<u8>, RenderError> {
    render_gif_with_progress(scene, opts, &mut |_, _| {})
}

/// [`render_gif`], calling `progress(done, frames)` after each frame is drawn: the longest
/// GIFs take half a minute, and a caller said nothing all that time.
pub fn render_gif_with_progress(
    scene: &Scene,
    opts: &RenderOptions,
    progress: &mut dyn FnMut(usize, usize),
) -> Result<Vec<u8>, RenderError> {
    // The frames set their own steps below: a step given here would be dropped unsaid.
    if let Some(step) = opts.step {
        return Err(RenderError::StepOfAnimation(step));
    }
    let view = View::fit(scene, opts)?;
    let frames = scene.num_steps().clamp(1, MAX_GIF_FRAMES) as u64;
    let pixels = frames * view.width as u64 * view.height as u64;
    if pixels > MAX_GIF_PIXELS {
        // The width that fits (the height follows it): the pixels grow as its square.
        let fits = (view.width as f64 * (MAX_GIF_PIXELS as f64 / pixels as f64).sqrt()) as u64;
        return Err(RenderError::Size(format!(
            "a GIF of {frames} frames of {} x {} pixels is {:.1} billion pixels, over the {} \
             billion one may take (minutes to draw, gigabytes to keep): {}",
            view.width,
            view.height,
            pixels as f64 / 1e9,
            MAX_GIF_PIXELS / 1_000_000_000,
            if fits >= 64 {
                format!("give --width {fits} or less, or draw one step (--step N, as PNG or SVG)")
            } else {
                "draw one step (--step N, as PNG or SVG)".into()
            }
        )));
    }
    let mut base = RasterCanvas::new(&view)?;
    draw_map(&mut base, scene, &view);
    // In the same corner in every frame: placed once, by the whole recording.
    let legend = legend_rect(&base, scene, &view, opts);
    let (w, h) = (view.width as u16, view.height as u16);
    let err = |e: gif::EncodingError| RenderError::Encode {
        format: "GIF",
        message: e.to_string(),
    };
    let mut out = Vec::new();
    {
        let mut enc = gif::Encoder::new(&mut out, w, h, &palette()).map_err(err)?;
        enc.set_repeat(gif::Repeat::Infinite).map_err(err)?;
        let delay = ((scene.meta.dt * 100.0).round() as u16).max(2);
        let steps = scene.num_steps().max(1);
        let first = steps.saturating_sub(MAX_GIF_FRAMES);
        for step in first..steps {
            let mut c = RasterCanvas {
                pixmap: base.pixmap.clone(),
            };
            let frame_opts = RenderOptions {
                step: Some(step),
                ..opts.clone()
            };
            draw_agents(&mut c, scene, &view, step, &frame_opts);
            draw_overlay(&mut c, scene, &view, step, &frame_opts, legend);
            let px: Vec<u8> = c
                .pixmap
                .data()
                .chunks_exact(4)
                .map(|p| index(p[0], p[1], p[2]))
                .collect();
            let mut frame = gif::Frame::from_indexed_pixels(w, h, px, None);
            frame.delay = if step + 1 == steps { delay * 10 } else { delay };
            enc.write_frame(&frame).map_err(err)?;
            progress(step + 1 - first, steps - first);
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_frame_is_reported_as_it_is_drawn() {
        let scene = crate::io::load_scene(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("data/samples/yaml/highway_cut_in.yaml"),
            0,
            &crate::io::LoadOptions::default(),
        )
        .unwrap();
        let opts = RenderOptions {
            width: 64,
            ..RenderOptions::default()
        };
        let mut seen = Vec::new();
        let bytes = render_gif_with_progress(&scene, &opts, &mut |k, n| seen.push((k, n))).unwrap();
        let n = scene.num_steps();
        assert_eq!(seen, (1..=n).map(|k| (k, n)).collect::<Vec<_>>());
        assert_eq!(bytes, render_gif(&scene, &opts).unwrap());
    }
}
