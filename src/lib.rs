//! drivescript: controllable traffic simulation.
//!
//! Scenes are read from real driving data ([`io`]) into a world-frame [`scene::Scene`]: a road
//! map with its lane graph and agents with states at a fixed time step. [`geom`] holds the
//! geometry everything else stands on (Frenet frames, oriented boxes) and [`render`] draws
//! scenes and rollouts.
#![warn(missing_docs)]

pub mod cost;
pub mod eval;
pub mod geom;
pub mod io;
pub mod llm;
pub mod model;
pub mod render;
pub mod sample;
pub mod scene;
pub mod train;
