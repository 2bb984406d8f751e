//! A scene described for a language model (and a person choosing agents): every relevant agent
//! with its lane, Frenet position and neighbours, the lanes around them, and the time grid the
//! sampler uses. `drivescript inspect --agents` prints it; the LLM loop puts it in its prompt.
//!
//! Relations are measured on each agent's lane path (its current lane followed straight ahead
//! through successors, as `a.lane_path()` gives scripts): another agent is in the same lane
//! when its centre lies within half a lane width of the path, beside it when it lies in the
//! next lane over and their boxes overlap along the path (with 2 m to spare).

use std::collections::BTreeSet;
use std::fmt;

use serde::Serialize;

use super::{Agent, AgentId, LaneId, Scene, Turn};

/// Lane width assumed where the map gives no boundaries, metres.
const DEFAULT_LANE_WIDTH: f64 = 3.6;

/// What to describe.
#[derive(Debug, Clone, PartialEq)]
pub struct DescribeOptions {
    /// Most agents listed; the rest are counted. Agents in `keep` are always listed.
    pub max_agents: usize,
    /// Agents that must be listed (those a request names).
    pub keep: Vec<AgentId>,
    /// Future steps the sampler will simulate (the model's horizon).
    pub horizon: usize,
}

impl Default for DescribeOptions {
    fn default() -> Self {
        Self {
            max_agents: 30,
            keep: Vec::new(),
            horizon: 40,
        }
    }
}

/// Another agent and the bumper-to-bumper gap to it along the lane path, metres.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Gap {
    /// The other agent.
    pub id: AgentId,
    /// Bumper-to-bumper distance along the path (negative when the boxes overlap).
    pub gap: f64,
}

/// One agent at the current step.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct AgentDescription {
    /// Identifier, as scripts' `agent(id)` takes it.
    pub id: AgentId,
    /// `vehicle`, `pedestrian`, `cyclist` or `other`.
    #[serde(rename = "type")]
    pub agent_type: &'static str,
    /// Length and width, metres.
    pub size: [f64; 2],
    /// Speed, m/s.
    pub speed: f64,
    /// The lane it is on (`None` off the lane graph).
    pub lane: Option<LaneId>,
    /// Arc length on that lane, metres from its start.
    pub s: Option<f64>,
    /// Lateral offset from the lane centre, metres, positive to the left.
    pub d: Option<f64>,
    /// Nearest agent ahead in the same lane (along the lane path), within 100 m.
    pub ahead: Option<Gap>,
    /// Nearest agent behind in the same lane, within 100 m.
    pub behind: Option<Gap>,
    /// Same-direction lane to the left.
    pub left_lane: Option<LaneId>,
    /// Same-direction lane to the right.
    pub right_lane: Option<LaneId>,
    /// Agents beside it in the lane to the left.
    pub beside_left: Vec<AgentId>,
    /// Agents beside it in the lane to the right.
    pub beside_right: Vec<AgentId>,
    /// Whether its lane is the rightmost of its road.
    pub rightmost: Option<bool>,
}

/// One lane near the listed agents.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct LaneDescription {
    /// Identifier, as scripts' lane functions take it.
    pub id: LaneId,
    /// Centre-line length, metres.
    pub length: f64,
    /// Same-direction neighbours to the left.
    pub left: Vec<LaneId>,
    /// Same-direction neighbours to the right.
    pub right: Vec<LaneId>,
    /// Lanes it flows into (none: it ends, where the map ends or the lane does).
    pub successors: Vec<LaneId>,
    /// Lanes flowing into it.
    pub predecessors: Vec<LaneId>,
    /// Whether it is the rightmost lane of its road.
    pub rightmost: bool,
    /// Speed limit, m/s, where the map has one.
    pub speed_limit: Option<f64>,
    /// Whether it lies in an intersection.
    pub intersection: bool,
}

/// A scene described for a language model.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct SceneDescription {
    /// The scene's id.
    pub scenario: String,
    /// Seconds per step.
    pub dt: f64,
    /// Future steps the sampler simulates; script series have one entry per step, the first
    /// at `dt` after the current step.
    pub horizon: usize,
    /// Agents listed, nearest the centre of attention first (the ego or the first kept agent).
    pub agents: Vec<AgentDescription>,
    /// Agents present at the current step but not listed (over the cap).
    pub omitted: usize,
    /// The cap on listed agents.
    pub max_agents: usize,
    /// The lanes the listed agents are on, their neighbours and successors.
    pub lanes: Vec<LaneDescription>,
}

/// Most absent ids [`absent_kept`] names; the rest are counted. A script passing ten thousand
/// ids got all of them back in one line.
pub const MAX_ABSENT_SHOWN: usize = 10;

/// The ids of `keep` that `scene` does not hold, as a list to show (at most
/// [`MAX_ABSENT_SHOWN`] of them, each once, then "and N more"), or `None` when it holds them
/// all. Kept ids are the request's agents: one missing is a mistake to say, not a scene to
/// describe without it.
pub fn absent_kept(scene: &Scene, keep: &[AgentId]) -> Option<String> {
    let mut absent: Vec<AgentId> = keep
        .iter()
        .copied()
        .filter(|id| !scene.agents.iter().any(|a| a.id == *id))
        .collect();
    absent.sort_unstable();
    absent.dedup();
    if absent.is_empty() {
        return None;
    }
    let shown: Vec<String> = absent
        .iter()
        .take(MAX_ABSENT_SHOWN)
        .map(|id| id.to_string())
        .collect();
    let more = absent.len() - shown.len();
    Some(if more > 0 {
        format!(
            "{} and {more} more ({} in all)",
            shown.join(", "),
            absent.len()
        )
    } else {
        shown.join(", ")
    })
}

/// Describes `scene` at its current step.
pub fn describe(scene: &Scene, opts: &DescribeOptions) -> SceneDescription {
    let c = scene.meta.current_step;
    let present: Vec<&Agent> = scene
        .agents
        .iter()
        .filter(|a| a.states.get(c).is_some_and(|s| s.valid))
        .collect();
    let pos = |a: &Agent| a.states[c].position();
    let centre = opts
        .keep
        .iter()
        .chain(scene.meta.ego.iter())
        .find_map(|id| scene.agent(*id).filter(|a| a.states[c].valid))
        .or(present.first().copied())
        .map(pos);
    let mut order: Vec<&Agent> = present.clone();
    if let Some(o) = centre {
        order.sort_by(|a, b| {
            let d = |x: &Agent| (pos(x) - o).norm();
            d(a).total_cmp(&d(b)).then(a.id.cmp(&b.id))
        });
    }
    let kept: Vec<&Agent> = order
        .iter()
        .filter(|a| opts.keep.contains(&a.id))
        .copied()
        .collect();
    let mut listed: Vec<&Agent> = kept.clone();
    for a in &order {
        if listed.len() >= opts.max_agents.max(kept.len()) {
            break;
        }
        if !kept.iter().any(|k| k.id == a.id) {
            listed.push(a);
        }
    }
    let g = scene.map.graph();
    let mut lanes_seen = BTreeSet::new();
    let agents = listed
        .iter()
        .map(|a| {
            let st = a.states[c];
            let lane = scene.map.lane_at(pos(a), st.heading);
            let mut desc = AgentDescription {
                id: a.id,
                agent_type: a.agent_type.name(),
                size: [round(a.length, 1), round(a.width, 1)],
                speed: round(st.vx.hypot(st.vy), 1),
                lane,
                s: None,
                d: None,
                ahead: None,
                behind: None,
                left_lane: None,
                right_lane: None,
                beside_left: Vec::new(),
                beside_right: Vec::new(),
                rightmost: None,
            };
            let Some(lane) = lane else {
                return desc;
            };
            lanes_seen.insert(lane);
            let s = scene
                .map
                .lane(lane)
                .map(|l| round(l.centerline.nearest(&pos(a)).s, 1));
            desc.s = s;
            desc.left_lane = g.left(lane);
            desc.right_lane = g.right(lane);
            desc.rightmost = Some(g.is_rightmost(lane));
            let along = s.unwrap_or(0.0);
            let Ok(path) = scene
                .map
                .lane_path(lane, along + 100.0, 100.0, Turn::Straight)
            else {
                return desc;
            };
            let me = path.frenet.project(pos(a));
            desc.d = Some(round(me.d, 2));
            let w = scene
                .map
                .lane_width_at(lane, pos(a))
                .filter(|w| *w > 1.0)
                .unwrap_or(DEFAULT_LANE_WIDTH);
            for o in &present {
                if o.id == a.id {
                    continue;
                }
                let f = path.frenet.project(pos(o));
                let ds = f.s - me.s;
                let half = 0.5 * (a.length + o.length);
                let dd = f.d - me.d;
                if ds.abs() > 100.0 {
                    continue;
                }
                if f.d.abs() <= 0.5 * w {
                    let gap = Gap {
                        id: o.id,
                        gap: round(ds.abs() - half, 1),
                    };
                    let slot = if ds > 0.0 {
                        &mut desc.ahead
                    } else {
                        &mut desc.behind
                    };
                    if slot.as_ref().is_none_or(|x| gap.gap < x.gap) {
                        *slot = Some(gap);
                    }
                } else if ds.abs() <= half + 2.0 && dd.abs() <= 1.5 * w {
                    if dd > 0.0 {
                        desc.beside_left.push(o.id);
                    } else {
                        desc.beside_right.push(o.id);
                    }
                }
            }
            desc
        })
        .collect::<Vec<_>>();
    // The agents' lanes, their neighbours and successors: what a script can name.
    let mut ids: BTreeSet<LaneId> = BTreeSet::new();
    for &l in &lanes_seen {
        ids.insert(l);
        for n in g.left_neighbors(l).iter().chain(g.right_neighbors(l)) {
            ids.insert(*n);
        }
        for n in g.successors(l) {
            ids.insert(*n);
        }
    }
    let lanes = ids
        .iter()
        .filter_map(|&id| {
            let l = scene.map.lane(id)?;
            Some(LaneDescription {
                id,
                length: round(l.centerline.length(), 1),
                left: g.left_neighbors(id).to_vec(),
                right: g.right_neighbors(id).to_vec(),
                successors: g.successors(id).to_vec(),
                predecessors: g.predecessors(id).to_vec(),
                rightmost: g.is_rightmost(id),
                speed_limit: l.speed_limit.map(|v| round(v, 1)),
                intersection: l.is_intersection,
            })
        })
        .collect();
    SceneDescription {
        scenario: scene.meta.scenario_id.clone(),
        dt: scene.meta.dt,
        horizon: opts.horizon,
        omitted: present.len() - agents.len(),
        max_agents: opts.max_agents,
        agents,
        lanes,
    }
}

fn round(v: f64, digits: i32) -> f64 {
    let k = 10f64.powi(digits);
    (v * k).round() / k
}

fn ids(v: &[LaneId]) -> String {
    if v.is_empty() {
        "none".into()
    } else {
        v.iter()
            .map(|x| x.to_string())
            .collect::<Vec<_>>()
            .join(", ")
    }
}

/// Plain text, one line per agent and lane, as the LLM prompt and `inspect --agents` show it.
impl fmt::Display for SceneDescription {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        writeln!(
            f,
            "scene {}: {} future steps of {} s (series start {} s after the current step and \
             end at {:.1} s)",
            self.scenario,
            self.horizon,
            self.dt,
            self.dt,
            self.horizon as f64 * self.dt
        )?;
        writeln!(
            f,
            "agents ({} listed{}):",
            self.agents.len(),
            if self.omitted > 0 {
                format!(
                    ", {} more farther away not listed (cap {})",
                    self.omitted, self.max_agents
                )
            } else {
                String::new()
            }
        )?;
        for a in &self.agents {
            write!(
                f,
                "- {} {}: {} m/s, {}x{} m",
                a.agent_type, a.id, a.speed, a.size[0], a.size[1]
            )?;
            match (a.lane, a.s, a.d) {
                (Some(l), Some(s), Some(d)) => write!(f, ", lane {l} at s = {s} m, d = {d} m")?,
                (Some(l), _, _) => write!(f, ", lane {l}")?,
                _ => write!(f, ", on no lane")?,
            }
            if a.rightmost == Some(true) {
                write!(f, " (rightmost)")?;
            }
            let mut rel = Vec::new();
            if let Some(g) = &a.ahead {
                rel.push(format!("{} ahead by {} m", g.id, g.gap));
            }
            if let Some(g) = &a.behind {
                rel.push(format!("{} behind by {} m", g.id, g.gap));
            }
            if let Some(l) = a.left_lane {
                rel.push(format!("left lane {l}"));
            }
            if let Some(l) = a.right_lane {
                rel.push(format!("right lane {l}"));
            }
            if !a.beside_left.is_empty() {
                rel.push(format!("beside on the left: {}", ids(&a.beside_left)));
            }
            if !a.beside_right.is_empty() {
                rel.push(format!("beside on the right: {}", ids(&a.beside_right)));
            }
            if rel.is_empty() {
                writeln!(f)?;
            } else {
                writeln!(f, "; {}", rel.join("; "))?;
            }
        }
        writeln!(f, "lanes:")?;
        for l in &self.lanes {
            write!(
                f,
                "- lane {}: {} m; left {}; right {}; successors {}",
                l.id,
                l.length,
                ids(&l.left),
                ids(&l.right),
                if l.successors.is_empty() {
                    "none (ends)".into()
                } else {
                    ids(&l.successors)
                }
            )?;
            if l.rightmost {
                write!(f, "; rightmost")?;
            }
            if let Some(v) = l.speed_limit {
                write!(f, "; limit {v} m/s")?;
            }
            if l.intersection {
                write!(f, "; in an intersection")?;
            }
            writeln!(f)?;
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    #[test]
    fn absent_kept_ids_are_listed_once_and_capped() {
        let scene = crate::io::yaml::read(
            &std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
                .join("data/samples/yaml/highway_cut_in.yaml"),
        )
        .unwrap();
        assert_eq!(super::absent_kept(&scene, &[4]), None);
        assert_eq!(
            super::absent_kept(&scene, &[88, 77, 4, 88]).as_deref(),
            Some("77, 88")
        );
        let many: Vec<i64> = (1000..6000).collect();
        let shown = super::absent_kept(&scene, &many).unwrap();
        assert_eq!(
            shown,
            "1000, 1001, 1002, 1003, 1004, 1005, 1006, 1007, 1008, 1009 and 4990 more (5000 in all)"
        );
    }

    use super::*;
    use crate::io::yaml;
    use std::path::Path;

    fn highway() -> Scene {
        let p = Path::new(env!("CARGO_MANIFEST_DIR")).join("scripts/scenes/highway.yaml");
        crate::io::load_scene(&p, 0, &crate::io::LoadOptions::default()).unwrap()
    }

    #[test]
    fn known_lanes_gaps_and_neighbours_on_the_test_highway() {
        let s = highway();
        let d = describe(&s, &DescribeOptions::default());
        let a = |id| d.agents.iter().find(|a| a.id == id).unwrap();
        let len = |id| s.agent(id).unwrap().length;
        // Lanes 100-102 from the right; agent 1 in the middle at s = 60, 20 m/s.
        assert_eq!(
            (a(1).lane, a(1).left_lane, a(1).right_lane),
            (Some(101), Some(102), Some(100))
        );
        assert_eq!(
            (a(1).s, a(1).speed, a(1).rightmost),
            (Some(60.0), 20.0, Some(false))
        );
        assert!(a(1).d.unwrap().abs() < 0.01);
        // Agents 4 (s = 20) and 2 (s = 70) share the rightmost lane, 50 m apart centre to
        // centre.
        let gap = round(50.0 - 0.5 * (len(2) + len(4)), 1);
        assert_eq!(a(4).ahead, Some(Gap { id: 2, gap }));
        assert_eq!(a(2).behind, Some(Gap { id: 4, gap }));
        assert_eq!((a(2).rightmost, a(2).right_lane), (Some(true), None));
        assert_eq!(a(3).left_lane, None);
        // Nobody is beside anybody here (the nearest pair across lanes is 10 m apart).
        assert!(d
            .agents
            .iter()
            .all(|a| a.beside_left.is_empty() && a.beside_right.is_empty()));
        // The lanes: 100-102 and their successors 200-202, with the limit.
        let ids: Vec<LaneId> = d.lanes.iter().map(|l| l.id).collect();
        assert_eq!(ids, vec![100, 101, 102, 200, 201, 202]);
        let l100 = &d.lanes[0];
        assert_eq!((l100.successors.clone(), l100.rightmost), (vec![200], true));
        assert_eq!(l100.speed_limit, Some(29.0));
        let text = d.to_string();
        assert!(text.contains("- vehicle 4: 18 m/s"), "{text}");
        assert!(text.contains(&format!("2 ahead by {gap} m")), "{text}");
        assert!(text.contains("40 future steps of 0.1 s"), "{text}");
    }

    #[test]
    fn beside_and_the_cap_that_keeps_named_agents() {
        let text = "steps: 2\ncurrent_step: 0\nroad: {lanes: 2, lane_width: 3.5, length: 200}\nagents:\n  - {id: 1, lane: 0, s: 50, speed: 10}\n  - {id: 2, lane: 1, s: 52, speed: 10}\n  - {id: 3, lane: 0, s: 90, speed: 10}\n  - {id: 4, lane: 1, s: 150, speed: 10}\n";
        let s = yaml::parse(Path::new("t.yaml"), text).unwrap();
        let d = describe(&s, &DescribeOptions::default());
        let a = |id| d.agents.iter().find(|a| a.id == id).unwrap().clone();
        assert_eq!(
            (a(1).beside_left.clone(), a(2).beside_right.clone()),
            (vec![2], vec![1])
        );
        assert!(a(1).beside_right.is_empty() && a(3).beside_left.is_empty());
        // A cap of 2 lists the kept agent and the one nearest it, and counts the rest.
        let d = describe(
            &s,
            &DescribeOptions {
                max_agents: 2,
                keep: vec![4],
                horizon: 40,
            },
        );
        let listed: Vec<AgentId> = d.agents.iter().map(|a| a.id).collect();
        assert_eq!((listed, d.omitted), (vec![4, 3], 2));
        assert!(d
            .to_string()
            .contains("2 more farther away not listed (cap 2)"));
    }
}
