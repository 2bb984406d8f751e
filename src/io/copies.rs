//! Scenario ids read more than once from a corpus: every copy is cut into windows, so a
//! scenario copied into a second folder (or a TFRecord holding it twice) weighed twice in
//! training and in a corpus's counts, and nothing said so.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

/// How many repeated scenarios [`ScenarioCopies::warnings`] names before it counts the rest.
const NAMED: usize = 5;

/// The files each scenario id was read from, in the order they were met.
#[derive(Debug, Default, Clone)]
pub struct ScenarioCopies {
    seen: BTreeMap<String, Vec<PathBuf>>,
}

impl ScenarioCopies {
    /// No scenario read yet.
    pub fn new() -> Self {
        Self::default()
    }

    /// Notes that scenario `id` was read from `file` (once per record where a file holds it
    /// more than once).
    pub fn add(&mut self, id: &str, file: &Path) {
        self.seen
            .entry(id.to_string())
            .or_default()
            .push(file.to_path_buf());
    }

    /// The ids read more than once, each with the files it came from (a file as often as
    /// it held the id), in id order.
    pub fn repeated(&self) -> Vec<(&str, &[PathBuf])> {
        self.seen
            .iter()
            .filter(|(_, f)| f.len() > 1)
            .map(|(id, f)| (id.as_str(), f.as_slice()))
            .collect()
    }

    /// One line per repeated scenario, for the first few, then one counting the others;
    /// none where every scenario was read once.
    pub fn warnings(&self) -> Vec<String> {
        let repeated = self.repeated();
        let mut out: Vec<String> = repeated
            .iter()
            .take(NAMED)
            .map(|(id, files)| {
                let mut shown: Vec<String> = Vec::new();
                for f in *files {
                    let f = super::name::one_line(&f.display().to_string());
                    if !shown.contains(&f) {
                        shown.push(f);
                    }
                }
                format!(
                    "scenario \"{}\" was read {} times (from {}): each copy's windows are \
                     counted, so it weighs {} times as much as a scenario read once; give each \
                     scenario once to weigh it once",
                    super::name::shown(id),
                    files.len(),
                    super::name::first_few(&shown, 3),
                    files.len()
                )
            })
            .collect();
        if repeated.len() > NAMED {
            out.push(format!(
                "{} more scenarios were read more than once",
                repeated.len() - NAMED
            ));
        }
        out
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_scenario_read_twice_is_named_with_its_files_and_the_rest_counted() {
        let mut c = ScenarioCopies::new();
        c.add("A-1", Path::new("x/a.xml"));
        c.add("B-1", Path::new("x/b.xml"));
        assert!(c.warnings().is_empty());
        c.add("A-1", Path::new("y/a.xml"));
        let w = c.warnings();
        assert_eq!(w.len(), 1, "{w:?}");
        assert!(
            w[0].contains("\"A-1\" was read 2 times (from x/a.xml, y/a.xml)"),
            "{w:?}"
        );
        // One file holding it twice is named once, with both reads counted.
        c.add("B-1", Path::new("x/b.xml"));
        assert!(c.warnings()[1].contains("\"B-1\" was read 2 times (from x/b.xml)"));
        for k in 0..10 {
            c.add(&format!("C-{k}"), Path::new("p"));
            c.add(&format!("C-{k}"), Path::new("q"));
        }
        let w = c.warnings();
        assert_eq!(w.len(), NAMED + 1, "{w:?}");
        assert_eq!(w[NAMED], "7 more scenarios were read more than once");
    }
}
