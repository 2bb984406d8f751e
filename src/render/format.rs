//! The picture formats `render` writes, told by the output's name, and how an existing file of
//! each is recognised: `render -o` replaces only a picture of the same format (an earlier
//! render), never a user's file that happens to have the name.

use std::path::Path;

use super::{render_gif, render_png, render_svg, RenderError, RenderOptions};
use crate::scene::Scene;

/// A picture format.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum PictureFormat {
    /// `.svg`.
    Svg,
    /// `.png`.
    Png,
    /// `.gif`, every step a frame.
    Gif,
}

impl PictureFormat {
    /// The format `path`'s extension names (any case), or `None`.
    pub fn from_path(path: &Path) -> Option<Self> {
        let ext = path.extension()?.to_string_lossy().to_lowercase();
        match ext.as_str() {
            "svg" => Some(Self::Svg),
            "png" => Some(Self::Png),
            "gif" => Some(Self::Gif),
            _ => None,
        }
    }

    /// The kind of file, for messages.
    pub fn what(self) -> &'static str {
        match self {
            Self::Svg => "an SVG picture",
            Self::Png => "a PNG picture",
            Self::Gif => "a GIF picture",
        }
    }

    /// Whether `bytes` are a picture of this format: PNG and GIF by their magic bytes, SVG by
    /// an XML document whose root element is `svg`.
    pub fn recognises(self, bytes: &[u8]) -> bool {
        match self {
            Self::Png => bytes.starts_with(b"\x89PNG\r\n\x1a\n"),
            Self::Gif => bytes.starts_with(b"GIF87a") || bytes.starts_with(b"GIF89a"),
            Self::Svg => {
                let text = std::str::from_utf8(bytes).unwrap_or("");
                let text = text.strip_prefix('\u{feff}').unwrap_or(text);
                let options = roxmltree::ParsingOptions {
                    allow_dtd: true,
                    ..roxmltree::ParsingOptions::default()
                };
                roxmltree::Document::parse_with_options(text, options)
                    .is_ok_and(|d| d.root_element().tag_name().name() == "svg")
            }
        }
    }

    /// Whether the file at `path` is a picture of this format ([`PictureFormat::recognises`]):
    /// PNG and GIF by their first bytes (an animation can be large), SVG read whole (within
    /// [`crate::io::MAX_SCENE_BYTES`]).
    pub fn holds_own(self, path: &Path) -> bool {
        use std::io::Read;
        match self {
            Self::Svg => crate::io::read_regular(path, crate::io::MAX_SCENE_BYTES, self.what())
                .is_ok_and(|b| self.recognises(&b)),
            Self::Png | Self::Gif => {
                let mut head = Vec::with_capacity(8);
                std::fs::File::open(path)
                    .and_then(|f| f.take(8).read_to_end(&mut head))
                    .is_ok()
                    && self.recognises(&head)
            }
        }
    }

    /// `scene` drawn in this format.
    pub fn render(self, scene: &Scene, opts: &RenderOptions) -> Result<Vec<u8>, RenderError> {
        match self {
            Self::Svg => render_svg(scene, opts).map(String::into_bytes),
            Self::Png => render_png(scene, opts),
            Self::Gif => render_gif(scene, opts),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn each_format_recognises_its_own_pictures_only() {
        let scene = crate::io::load_scene(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("data/samples/yaml/highway_cut_in.yaml"),
            0,
            &crate::io::LoadOptions::default(),
        )
        .unwrap();
        let opts = RenderOptions {
            width: 64,
            ..RenderOptions::default()
        };
        let all = [PictureFormat::Svg, PictureFormat::Png, PictureFormat::Gif];
        for f in all {
            let bytes = f.render(&scene, &opts).unwrap();
            for g in all {
                assert_eq!(g.recognises(&bytes), f == g, "{f:?} read as {g:?}");
            }
        }
        let dir = tempfile::tempdir().unwrap();
        for f in all {
            let p = dir.path().join("picture");
            std::fs::write(&p, f.render(&scene, &opts).unwrap()).unwrap();
            assert!(f.holds_own(&p), "{f:?}");
            std::fs::write(&p, "steps: 30\nagents: []\n").unwrap();
            assert!(!f.holds_own(&p), "{f:?}");
            assert!(!f.recognises(b"steps: 30\nagents: []\n"), "{f:?}");
            assert!(!f.recognises(b""), "{f:?}");
        }
        assert!(PictureFormat::Svg.recognises(
            b"<?xml version=\"1.0\"?>\n<!DOCTYPE svg PUBLIC \"-//W3C//DTD SVG 1.1//EN\" \"x\">\n<svg xmlns=\"http://www.w3.org/2000/svg\"/>"
        ));
        assert!(!PictureFormat::Svg.recognises(b"<html><svg/></html>"));
        assert_eq!(
            PictureFormat::from_path(Path::new("a.PNG")),
            Some(PictureFormat::Png)
        );
        assert_eq!(PictureFormat::from_path(Path::new("a.yaml")), None);
    }
}
