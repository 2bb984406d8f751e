//! Pictures of scenes: SVG, PNG and animated GIF.
