//! The scene files `convert` writes, told by the output's name, and what an existing file must
//! hold for `convert -o` to replace it: a file of the same format that its reader accepts,
//! holding one scenario (what `convert` writes), so that a user's other data (a YAML of their
//! own that does not parse, a many-scenario TFRecord, a scene JSON of another format) is never
//! replaced.

use std::path::Path;

use super::{check_replaces_own, rollout::Rollout, womd, write_atomic, yaml, IoError};
use crate::scene::Scene;

/// A format `convert` writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SceneOutput {
    /// drivescript YAML (map and agents): `.yaml`, `.yml`.
    Yaml,
    /// A rollout of the recorded trajectories: `.json`.
    Rollout,
    /// A Waymo Open Motion Dataset TFRecord of one scenario: `.tfrecord`,
    /// `*.tfrecord-NNNNN-of-NNNNN`.
    Tfrecord,
}

impl SceneOutput {
    /// The format `path`'s name asks for, or `None` for a name of no format `convert` writes.
    pub fn from_path(path: &Path) -> Option<Self> {
        let name = path.to_string_lossy().to_lowercase();
        if name.ends_with(".yaml") || name.ends_with(".yml") {
            Some(Self::Yaml)
        } else if name.ends_with(".json") {
            Some(Self::Rollout)
        } else if name.ends_with(".tfrecord") || name.contains(".tfrecord-") {
            Some(Self::Tfrecord)
        } else {
            None
        }
    }

    /// The kind of file, for messages.
    pub fn what(self) -> &'static str {
        match self {
            Self::Yaml => "a drivescript YAML scene",
            Self::Rollout => "a rollout JSON",
            Self::Tfrecord => "a WOMD TFRecord of one scenario",
        }
    }

    /// Whether the file at `path` holds what this format's writer writes: its reader accepts
    /// it, and (a TFRecord) it holds one scenario.
    pub fn holds_own(self, path: &Path) -> bool {
        match self {
            Self::Yaml => yaml::read(path).is_ok(),
            Self::Rollout => Rollout::read(path).is_ok(),
            Self::Tfrecord => womd::read_file(path).is_ok_and(|mut records| {
                matches!(records.next(), Some(Ok(_))) && records.next().is_none()
            }),
        }
    }

    /// Refuses an existing regular file at `output` that does not hold what this format
    /// writes ([`SceneOutput::holds_own`], [`check_replaces_own`]).
    pub fn check_replaces_own(self, output: &Path, flag: &str) -> Result<(), IoError> {
        check_replaces_own(output, flag, self.what(), |p| self.holds_own(p))
    }

    /// What of `scene` this format cannot hold, one line each ("12 drivable areas ..."), for
    /// `convert` to say: a WOMD TFRecord has no drivable areas and no lane boundaries of its
    /// own (its lanes point into road lines), no static agents and no bus lanes. A
    /// file that reads back without them would otherwise change what `eval` counts as off the
    /// road, and what `lane_width` and `f.to_left` give, without a word. Empty for YAML, which
    /// holds every part, and for a rollout, which holds trajectories by design.
    pub fn left_out(self, scene: &Scene) -> Vec<String> {
        let map = &scene.map;
        let mut lost = Vec::new();
        match self {
            // A rollout holds trajectories only, as its name says; YAML holds every part.
            Self::Yaml | Self::Rollout => {}
            Self::Tfrecord => {
                let areas = map.drivable_areas().len();
                if areas > 0 {
                    lost.push(format!(
                        "{areas} drivable area(s): WOMD has none, so the file's off-road \
                         distance comes from its road edges alone"
                    ));
                }
                let bounded = map
                    .lanes()
                    .iter()
                    .filter(|l| l.left_boundary.is_some() || l.right_boundary.is_some())
                    .count();
                if bounded > 0 {
                    lost.push(format!(
                        "the boundaries of {bounded} lane(s): WOMD lanes have none of their own, \
                         so lane_width and f.to_left/f.to_right fall back to a 3.6 m lane"
                    ));
                }
                let parked = scene.agents.iter().filter(|a| a.is_static).count();
                if parked > 0 {
                    lost.push(format!(
                        "which {parked} agent(s) are static: WOMD has no such flag, so they \
                         read back as agents that the sampler moves"
                    ));
                }
                let bus = map
                    .lanes()
                    .iter()
                    .filter(|l| l.lane_type == crate::scene::LaneType::Bus)
                    .count();
                if bus > 0 {
                    lost.push(format!(
                        "the type of {bus} bus lane(s): WOMD has no bus lanes; they are written \
                         as surface streets"
                    ));
                }
            }
        }
        lost
    }

    /// Writes `scene` to `path` in this format, atomically (devices and pipes in place).
    pub fn write(self, path: &Path, scene: &Scene) -> Result<(), IoError> {
        match self {
            Self::Yaml => write_atomic(path, yaml::to_yaml(scene).as_bytes()),
            Self::Rollout => Rollout::from_scene(scene).write(path),
            Self::Tfrecord => womd::write_file(path, std::slice::from_ref(scene)),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, LoadOptions};

    #[test]
    fn an_output_replaces_only_a_file_of_its_own_format_holding_one_scenario() {
        let dir = tempfile::tempdir().unwrap();
        let scene = load_scene(
            &Path::new(env!("CARGO_MANIFEST_DIR")).join("data/samples/yaml/highway_cut_in.yaml"),
            0,
            &LoadOptions::default(),
        )
        .unwrap();
        let p = |name: &str| dir.path().join(name);
        for (name, format) in [
            ("a.yaml", SceneOutput::Yaml),
            ("a.json", SceneOutput::Rollout),
            ("a.tfrecord", SceneOutput::Tfrecord),
        ] {
            assert_eq!(SceneOutput::from_path(&p(name)), Some(format));
            // New, then an earlier output of its own: both may be written.
            format.check_replaces_own(&p(name), "-o").unwrap();
            format.write(&p(name), &scene).unwrap();
            format.check_replaces_own(&p(name), "-o").unwrap();
            // A file of another kind under the name: refused, naming it.
            std::fs::write(p(name), "my notes: keep them\n").unwrap();
            let e = format
                .check_replaces_own(&p(name), "-o")
                .unwrap_err()
                .to_string();
            assert!(
                e.contains(&format!(
                    "{name}: -o: already exists and is not {}",
                    format.what()
                )) && e.contains("remove it first or write to another file"),
                "{e}"
            );
        }
        // A TFRecord of two scenarios is not what convert writes.
        womd::write_file(&p("two.tfrecord"), &[scene.clone(), scene.clone()]).unwrap();
        assert!(!SceneOutput::Tfrecord.holds_own(&p("two.tfrecord")));
        // A pipe or device is written in place, not replaced: nothing to refuse.
        SceneOutput::Yaml
            .check_replaces_own(Path::new("/dev/null"), "-o")
            .unwrap();
        assert_eq!(SceneOutput::from_path(&p("a.txt")), None);
    }
}
