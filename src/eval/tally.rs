//! One method's results over many scenes: what `eval` prints as a row of its tables, whole and
//! by group (map kind, agent type), and what a shard's `--json` keeps for `--merge`.
//!
//! The groups answer where a model fails: a model can match the log on highways and leave the
//! road at junctions, or drive cars well and cyclists badly, and one pooled row hides both.
//! Per-agent figures (displacement, collision, off-road, realism histograms, kinematic flags)
//! are restricted to the group's agents; figures of a whole scene (scene collision rate,
//! placement MMD, behaviour verdicts) appear only in the groups of a map kind, which hold whole
//! scenes.

use std::collections::BTreeMap;

use serde::{Deserialize, Serialize};
use serde_json::json;

use super::asked;
use super::behaviors::{Behavior, CheckError, Verdict};
use super::kinematic::{self, KinematicLimits, Violation};
use super::metrics::{self, Kinematics};
use crate::cost::Params;
use crate::scene::{Agent, AgentType, Map, Scene, Turn};

/// What an evaluation measures.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Task {
    /// Futures given the history, against the log.
    Conditional,
    /// Free futures, judged by their distribution.
    Unconditional,
    /// Whether a behaviour was achieved.
    Behaviour,
}

impl Task {
    /// The name `eval --task` and the `--json` file use.
    pub fn name(self) -> &'static str {
        match self {
            Task::Conditional => "conditional",
            Task::Unconditional => "unconditional",
            Task::Behaviour => "behaviour",
        }
    }

    /// Parses [`Task::name`].
    pub fn from_name(s: &str) -> Option<Self> {
        Some(match s {
            "conditional" => Task::Conditional,
            "unconditional" => Task::Unconditional,
            "behaviour" => Task::Behaviour,
            _ => return None,
        })
    }
}

/// Whether a map is a highway or has the junctions of a town.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub enum MapKind {
    /// At most one lane turns (a ramp).
    Highway,
    /// Lanes turn left or right ([`Map::turn_of`]): junctions.
    Urban,
}

impl MapKind {
    /// Lower-case name.
    pub fn name(self) -> &'static str {
        match self {
            MapKind::Highway => "highway",
            MapKind::Urban => "urban",
        }
    }
}

/// The kind of `map`, from its geometry rather than its source, since one corpus can hold
/// both (NGSIM's Lankershim Boulevard has junctions; a town's bypass has none): urban when at
/// least two lanes turn by more than [`crate::scene::TURN_THRESHOLD`] from start to end. One
/// curving lane is a ramp: three of NGSIM's US 101 maps have one lane that turns 79°, and no
/// other; every Lankershim map has more than two turning lanes, as do 1,009 of the 1,036
/// maps of the CommonRoad scenario factory (the other 27 are stretches between junctions).
pub fn map_kind(map: &Map) -> MapKind {
    let turning = map
        .lanes()
        .iter()
        .filter(|l| matches!(map.turn_of(l.id), Some(Turn::Left | Turn::Right)))
        .count();
    if turning >= 2 {
        MapKind::Urban
    } else {
        MapKind::Highway
    }
}

/// The agents and scenes a group's row covers.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord)]
pub struct Group {
    /// Scenes of this kind only, or all.
    pub map: Option<MapKind>,
    /// Agents of this type only, or all that the whole row counts.
    pub agent: Option<AgentType>,
}

impl Group {
    /// Its label: "urban", "cyclists", "highway vehicles".
    pub fn label(&self) -> String {
        match (self.map, self.agent) {
            (None, None) => "all".into(),
            (Some(m), None) => m.name().into(),
            (None, Some(t)) => format!("{}s", t.name()),
            (Some(m), Some(t)) => format!("{} {}s", m.name(), t.name()),
        }
    }

    fn keeps(&self, a: &Agent) -> bool {
        self.agent.is_none_or(|t| a.agent_type == t)
    }
}

/// One method's results over all scenes.
#[derive(Debug, Default, Serialize, Deserialize)]
pub struct Tally {
    /// Scenes scored.
    pub scenes: usize,
    /// Per scene, mean ADE over its agents.
    pub ade: Vec<f64>,
    /// Per scene, mean FDE.
    pub fde: Vec<f64>,
    /// Per scene, mean minimum ADE over samples.
    pub min_ade: Vec<f64>,
    /// Per scene, mean minimum FDE.
    pub min_fde: Vec<f64>,
    /// Per scene, fraction of agents that collide.
    pub collision: Vec<f64>,
    /// Per scene, fraction of vehicles that leave the road.
    pub offroad: Vec<f64>,
    /// Kinematics of the samples, pooled.
    pub sim_kin: Kinematics,
    /// Kinematics of the log, pooled.
    pub log_kin: Kinematics,
    /// Per scene, the scene collision rate.
    pub scr: Vec<f64>,
    /// Per scene, MMD² of nearest-object distances.
    pub mmd_near: Vec<f64>,
    /// Per scene, MMD² of road-edge distances.
    pub mmd_edge: Vec<f64>,
    /// Samples whose behaviour was achieved plausibly.
    pub passed: usize,
    /// Samples whose behaviour was achieved.
    pub achieved: usize,
    /// Samples checked.
    pub checked: usize,
    /// Per judged agent of every sample: implausible at all.
    pub implausible: Vec<Option<bool>>,
    /// Per agent of every sample (unconditional and behaviour tasks): whether its box overlaps
    /// another's at some future step (the pair an accident names excepted). The whole row and
    /// map-kind rows count vehicles; agent-type rows their type.
    #[serde(default)]
    pub collided: Vec<Option<bool>>,
    /// Per [`Violation::ALL`], as `implausible`.
    pub by_kind: [Vec<Option<bool>>; 6],
    /// One JSON row per scene (whole row only).
    pub per_scene: Vec<serde_json::Value>,
    /// Seconds spent scoring.
    pub seconds: f64,
    /// The rows of each group, by [`Group::label`] (whole row only; empty in files written
    /// before groups).
    #[serde(default)]
    pub groups: BTreeMap<String, Tally>,
}

/// A figure for a scene's JSON row: `null` where there is none, `"NaN"` / `"inf"` where it is
/// not finite ([`crate::io::json::number`]).
fn num(v: Option<f64>) -> serde_json::Value {
    v.map_or(serde_json::Value::Null, crate::io::json::number)
}

fn mean(v: &[f64]) -> Option<f64> {
    (!v.is_empty()).then(|| v.iter().sum::<f64>() / v.len() as f64)
}

/// `flags` (one per agent of `s`) with every agent `keep` rejects left out (`None`).
fn only(
    s: &Scene,
    mut flags: Vec<Option<bool>>,
    keep: impl Fn(&Agent) -> bool,
) -> Vec<Option<bool>> {
    for (f, a) in flags.iter_mut().zip(&s.agents) {
        if !keep(a) {
            *f = None;
        }
    }
    flags
}

/// The groups a scene contributes to: its map kind, and per type of its road users that type
/// across maps and within its map kind.
pub fn groups_of(s: &Scene) -> Vec<Group> {
    let kind = map_kind(&s.map);
    let mut types: Vec<AgentType> = s
        .agents
        .iter()
        .map(|a| a.agent_type)
        .filter(|t| *t != AgentType::Other)
        .collect();
    types.sort();
    types.dedup();
    let mut g = vec![Group {
        map: Some(kind),
        agent: None,
    }];
    for t in types {
        g.push(Group {
            map: None,
            agent: Some(t),
        });
        g.push(Group {
            map: Some(kind),
            agent: Some(t),
        });
    }
    g
}

/// What sample `k` allowed, of `allowed` (one list per sample).
fn allowed_in(allowed: &[Vec<(i64, Violation)>], k: usize) -> &[(i64, Violation)] {
    allowed.get(k).map_or(&[], Vec::as_slice)
}

/// What a scene's scoring measures once, per agent, for the whole row and every group to
/// filter (each group keeps its own agents).
struct Measured<'a> {
    verdicts: &'a [Result<Verdict, CheckError>],
    /// Per sample, every agent's kinematic judgement, less what the request asks of it (a
    /// reverse's backing up, what the sample's scripts allow: [`asked::judged`]), as its
    /// verdict does not count it.
    judged: Vec<Vec<Option<kinematic::Judgement>>>,
    /// Of the first sample (conditional and unconditional tasks).
    collided: Vec<Option<bool>>,
    offroad: Vec<Option<bool>>,
    displacement: Vec<metrics::Displacement>,
    /// Over the samples, where there are several.
    min_displacement: Option<Vec<metrics::Displacement>>,
    /// Per sample of a behaviour task, collisions but those the behaviour asks for.
    contacts: Vec<Vec<Option<bool>>>,
}

impl<'a> Measured<'a> {
    fn new(
        task: Task,
        logged: &Scene,
        sims: &[Scene],
        behaviour: Option<(Behavior, &Params)>,
        allowed: &[Vec<(i64, Violation)>],
        verdicts: &'a [Result<Verdict, CheckError>],
    ) -> Self {
        let lim = KinematicLimits::default();
        let checks: Vec<(Behavior, Params)> =
            behaviour.map(|(b, p)| (b, p.clone())).into_iter().collect();
        let judged = sims
            .iter()
            .enumerate()
            .map(|(k, s)| asked::judged(s, &checks, allowed_in(allowed, k), &lim))
            .collect();
        let behaviour = behaviour.map(|b| b.0);
        let sim = &sims[0];
        let conditional = task == Task::Conditional;
        Self {
            verdicts,
            judged,
            collided: if task == Task::Behaviour {
                Vec::new()
            } else {
                metrics::collided(sim)
            },
            offroad: if conditional {
                metrics::offroad(sim)
            } else {
                Vec::new()
            },
            displacement: if conditional {
                metrics::displacement(logged, sim)
            } else {
                Vec::new()
            },
            min_displacement: (conditional && sims.len() > 1)
                .then(|| metrics::min_displacement(logged, sims)),
            contacts: match behaviour {
                Some(b) => sims
                    .iter()
                    .zip(verdicts)
                    .map(|(s, v)| match v {
                        Ok(v) => metrics::collided_except(s, &b.contacts(&v.named)),
                        Err(_) => Vec::new(),
                    })
                    .collect(),
                None => Vec::new(),
            },
        }
    }
}

/// The largest distance a figure may hold, metres: points of a scene lie within
/// [`crate::geom::MAX_COORD`] of the origin, so none are farther apart than 2√2 of it.
pub const MAX_DISTANCE: f64 = 3.0e7;

impl Tally {
    /// Scores one scene: `logged` (the reference), the method's samples `sims` (at least one),
    /// the behaviour and its parameters for [`Task::Behaviour`], the samples' unguided twins
    /// when a behaviour is judged against them, and per sample the motion its scripts allowed
    /// (`allowed`, from [`asked::kinds`]; a sample past its end allowed nothing), which counts
    /// as asked as `ask` and `simulate` counted it ([`asked`]). Adds to this row and to each
    /// group of the scene ([`groups_of`]).
    pub fn score(
        &mut self,
        task: Task,
        logged: &Scene,
        sims: &[Scene],
        behaviour: Option<(Behavior, &Params)>,
        unguided: Option<&[Scene]>,
        allowed: &[Vec<(i64, Violation)>],
    ) {
        let t0 = std::time::Instant::now();
        // Every sample is judged, each against its own unguided twin: the rate is per sample,
        // as `simulate` and `ask` judge them.
        let verdicts: Vec<Result<Verdict, CheckError>> = match behaviour {
            Some((b, p)) => {
                let checks = [(b, p.clone())];
                sims.iter()
                    .enumerate()
                    .map(|(k, s)| {
                        let twin = unguided.and_then(|u| u.get(k));
                        asked::verdicts(&checks, s, twin, allowed_in(allowed, k))
                            .map(|mut v| v.remove(0))
                    })
                    .collect()
            }
            None => Vec::new(),
        };
        let m = Measured::new(task, logged, sims, behaviour, allowed, &verdicts);
        let whole = Group {
            map: None,
            agent: None,
        };
        let mut row = self.add(task, logged, sims, &m, whole);
        let groups = groups_of(logged);
        row["map"] = json!(groups[0].map.map_or("", MapKind::name));
        self.per_scene.push(row);
        for g in groups {
            self.groups
                .entry(g.label())
                .or_default()
                .add(task, logged, sims, &m, g);
        }
        self.seconds += t0.elapsed().as_secs_f64();
    }

    /// Adds a scene's figures for the agents of `g`; returns the scene's JSON row.
    fn add(
        &mut self,
        task: Task,
        logged: &Scene,
        sims: &[Scene],
        m: &Measured,
        g: Group,
    ) -> serde_json::Value {
        self.scenes += 1;
        let sim = &sims[0];
        let mut row = json!({"scene": logged.meta.scenario_id});
        let keep = |a: &Agent| g.keeps(a);
        // Collisions count vehicles unless the group is of one type.
        let collider = |a: &Agent| match g.agent {
            Some(t) => a.agent_type == t,
            None => a.agent_type == AgentType::Vehicle,
        };
        let (mut flagged, mut slots) = (0, 0);
        for (s, judged) in sims.iter().zip(&m.judged) {
            let any = only(s, kinematic::flags(judged, None), keep);
            flagged += any.iter().filter(|f| **f == Some(true)).count();
            slots += any.len();
            self.implausible.extend(any);
            for (k, v) in Violation::ALL.iter().enumerate() {
                self.by_kind[k].extend(only(s, kinematic::flags(judged, Some(*v)), keep));
            }
        }
        row["implausible_vehicles"] = json!(flagged);
        // The per-agent flags this scene added (agents × samples): `check` holds a shard's
        // lists to the sum of these, so an edited list cannot outweigh the scenes scored.
        row["agent_samples"] = json!(slots);
        let whole_scenes = g.agent.is_none();
        match task {
            Task::Conditional => {
                let of_group = |d: &[metrics::Displacement]| -> Vec<metrics::Displacement> {
                    d.iter()
                        .filter(|x| logged.agent(x.agent).is_some_and(keep))
                        .copied()
                        .collect()
                };
                let d = of_group(&m.displacement);
                let (ade, fde) = (
                    mean(&d.iter().map(|x| x.ade).collect::<Vec<_>>()),
                    mean(&d.iter().map(|x| x.fde).collect::<Vec<_>>()),
                );
                if let (Some(a), Some(f)) = (ade, fde) {
                    self.ade.push(a);
                    self.fde.push(f);
                }
                if let Some(min) = &m.min_displacement {
                    let m = of_group(min);
                    // Both or neither: a NaN pushed here was written as null and refused by
                    // --merge.
                    if let (Some(a), Some(f)) = (
                        mean(&m.iter().map(|x| x.ade).collect::<Vec<_>>()),
                        mean(&m.iter().map(|x| x.fde).collect::<Vec<_>>()),
                    ) {
                        self.min_ade.push(a);
                        self.min_fde.push(f);
                    }
                }
                let col = metrics::rate(&only(sim, m.collided.clone(), keep));
                let off = metrics::rate(&only(sim, m.offroad.clone(), keep));
                self.collision.extend(col);
                self.offroad.extend(off);
                for s in sims {
                    self.sim_kin.extend(&metrics::kinematics_of(s, keep));
                }
                self.log_kin.extend(&metrics::kinematics_of(logged, keep));
                row["ade"] = num(ade);
                row["fde"] = num(fde);
                row["collision_rate"] = num(col);
                row["offroad_rate"] = num(off);
            }
            Task::Unconditional => {
                self.collided
                    .extend(only(sim, m.collided.clone(), collider));
                if whole_scenes {
                    let scr = metrics::scene_collision_rate(sim, 0.1);
                    self.scr.extend(scr);
                    let (gn, ge) = metrics::placement(sim);
                    let (ln, le) = metrics::placement(logged);
                    let mn = metrics::mmd2(&gn, &ln, metrics::median_bandwidth(&gn, &ln));
                    let me = metrics::mmd2(&ge, &le, metrics::median_bandwidth(&ge, &le));
                    self.mmd_near.extend(mn);
                    self.mmd_edge.extend(me);
                    row["scene_collision_rate"] = num(scr);
                    row["mmd2_nearest_object"] = num(mn);
                    row["mmd2_road_edge"] = num(me);
                }
            }
            Task::Behaviour => {
                let mut rows = Vec::with_capacity(m.verdicts.len());
                for ((s, verdict), hit) in sims.iter().zip(m.verdicts).zip(&m.contacts) {
                    match verdict {
                        Ok(v) => {
                            self.collided.extend(only(s, hit.clone(), collider));
                            if whole_scenes {
                                self.checked += 1;
                                self.passed += v.passed as usize;
                                self.achieved += v.achieved as usize;
                            }
                            rows.push(json!(v));
                        }
                        Err(e) => {
                            row["error"] = json!(e.to_string());
                            break;
                        }
                    }
                }
                row["verdicts"] = json!(rows);
            }
        }
        row
    }

    /// Adds another shard's results for the same method. The counts are summed checked: an
    /// overflow is an error naming the count, not a wrapped table.
    pub fn absorb(&mut self, o: Tally) -> Result<(), String> {
        for (name, a, b) in [
            ("scenes", &mut self.scenes, o.scenes),
            ("passed", &mut self.passed, o.passed),
            ("achieved", &mut self.achieved, o.achieved),
            ("checked", &mut self.checked, o.checked),
        ] {
            *a = a
                .checked_add(b)
                .ok_or_else(|| format!("{name} is {b}, and the sum overflows"))?;
        }
        for (a, b) in [
            (&mut self.ade, o.ade),
            (&mut self.fde, o.fde),
            (&mut self.min_ade, o.min_ade),
            (&mut self.min_fde, o.min_fde),
            (&mut self.collision, o.collision),
            (&mut self.offroad, o.offroad),
            (&mut self.scr, o.scr),
            (&mut self.mmd_near, o.mmd_near),
            (&mut self.mmd_edge, o.mmd_edge),
        ] {
            a.extend(b);
        }
        self.sim_kin.extend(&o.sim_kin);
        self.log_kin.extend(&o.log_kin);
        self.implausible.extend(o.implausible);
        self.collided.extend(o.collided);
        for (a, b) in self.by_kind.iter_mut().zip(o.by_kind) {
            a.extend(b);
        }
        self.per_scene.extend(o.per_scene);
        self.seconds += o.seconds;
        for (k, g) in o.groups {
            self.groups
                .entry(k.clone())
                .or_default()
                .absorb(g)
                .map_err(|m| format!("groups[{k:?}].{m}"))?;
        }
        Ok(())
    }

    /// Checks an accumulator read back from a shard file (`eval --merge`): what [`Tally::score`]
    /// can write, and nothing else. Distances and MMD² finite and not negative, rates in
    /// [0, 1], kinematics finite (speeds and gaps not negative), passed ≤ achieved ≤ checked,
    /// one scene row per scene, no more figures than scenes, one flag per kind per judged
    /// agent; each group the same, within the whole row's scenes. The message names the field.
    pub fn check(&self) -> Result<(), String> {
        if self.per_scene.len() != self.scenes {
            return Err(format!(
                "scenes is {}, but per_scene holds {} scene rows (one per scene)",
                self.scenes,
                self.per_scene.len()
            ));
        }
        // Each row names its scene: the merge refuses a scene in two shard files by these
        // names, and a relabelled copy of a shard with its rows' names deleted was merged,
        // its scenes counted twice (issue 32).
        for (i, row) in self.per_scene.iter().enumerate() {
            match row.get("scene") {
                Some(serde_json::Value::String(name)) if !name.is_empty() => {}
                Some(other) => {
                    return Err(format!(
                        "per_scene[{i}].scene is {}: must be the scene's name",
                        crate::io::name::shown_counted(&other.to_string())
                    ))
                }
                None => {
                    return Err(format!(
                        "per_scene[{i}] has no scene: each row names the scene it scores"
                    ))
                }
            }
        }
        // Every per-agent list is held to the flags the scenes say they added: 100,000
        // `collided` entries in a shard of one scene were merged into the rate (issue 32).
        let mut slots: usize = 0;
        for (i, row) in self.per_scene.iter().enumerate() {
            let n = row
                .get("agent_samples")
                .and_then(serde_json::Value::as_u64)
                .and_then(|n| usize::try_from(n).ok())
                .ok_or_else(|| {
                    format!(
                        "per_scene[{i}].agent_samples is {}: must be the number of per-agent \
                         flags the scene added (agents × samples; files written before it was \
                         recorded cannot be merged: score the shard again)",
                        row.get("agent_samples").map_or("absent".to_string(), |v| {
                            crate::io::name::shown_counted(&v.to_string())
                        })
                    )
                })?;
            slots = slots
                .checked_add(n)
                .ok_or_else(|| format!("per_scene[{i}].agent_samples is {n}: the sum overflows"))?;
        }
        if self.implausible.len() != slots {
            return Err(format!(
                "implausible holds {} flags, and the scene rows' agent_samples sum to {slots}: \
                 one per agent of every sample",
                self.implausible.len()
            ));
        }
        self.check_figures()?;
        let labels: Vec<String> = group_order().iter().map(Group::label).collect();
        for (label, g) in &self.groups {
            let at = |m: String| format!("groups[{label:?}].{m}");
            if !labels.contains(label) {
                return Err(format!(
                    "groups[{label:?}]: not a group eval writes ({})",
                    labels.join(", ")
                ));
            }
            if g.scenes > self.scenes {
                return Err(at(format!(
                    "scenes is {}: more than the whole row's {}",
                    g.scenes, self.scenes
                )));
            }
            if !g.per_scene.is_empty() || !g.groups.is_empty() {
                return Err(at(
                    "per_scene and groups: a group holds none (the whole row does)".into(),
                ));
            }
            // A group's scenes are some of the whole row's, each adding as many flags.
            if g.implausible.len() > self.implausible.len() {
                return Err(at(format!(
                    "implausible holds {} flags: more than the whole row's {}",
                    g.implausible.len(),
                    self.implausible.len()
                )));
            }
            g.check_figures().map_err(at)?;
        }
        Ok(())
    }

    /// [`Tally::check`]'s figures, of the whole row or a group.
    fn check_figures(&self) -> Result<(), String> {
        let not_negative = |v: f64| v.is_finite() && v >= 0.0;
        // Two points of a scene lie within 1e7 m of the origin (`geom::MAX_COORD`), so no
        // distance between them exceeds 2√2·1e7 m; an ADE of 1e300 was merged and printed in
        // the table in 301 digits.
        let distance = |v: f64| not_negative(v) && v <= MAX_DISTANCE;
        let fraction = |v: f64| (0.0..=1.0).contains(&v);
        let finite = |v: f64| v.is_finite();
        // (field, figures, whether one is acceptable, what it must be)
        type Series<'a> = (&'a str, &'a [f64], &'a dyn Fn(f64) -> bool, &'a str);
        let series: [Series; 17] = [
            (
                "ade",
                &self.ade,
                &distance,
                "a distance: finite, 0 to 3e7 m",
            ),
            (
                "fde",
                &self.fde,
                &distance,
                "a distance: finite, 0 to 3e7 m",
            ),
            (
                "min_ade",
                &self.min_ade,
                &distance,
                "a distance: finite, 0 to 3e7 m",
            ),
            (
                "min_fde",
                &self.min_fde,
                &distance,
                "a distance: finite, 0 to 3e7 m",
            ),
            ("collision", &self.collision, &fraction, "a rate: 0 to 1"),
            ("offroad", &self.offroad, &fraction, "a rate: 0 to 1"),
            ("scr", &self.scr, &fraction, "a rate: 0 to 1"),
            (
                "mmd_near",
                &self.mmd_near,
                &not_negative,
                "an MMD²: finite, not negative",
            ),
            (
                "mmd_edge",
                &self.mmd_edge,
                &not_negative,
                "an MMD²: finite, not negative",
            ),
            (
                "sim_kin.speed",
                &self.sim_kin.speed,
                &not_negative,
                "a speed: finite, not negative",
            ),
            (
                "sim_kin.angular_speed",
                &self.sim_kin.angular_speed,
                &finite,
                "finite",
            ),
            ("sim_kin.accel", &self.sim_kin.accel, &finite, "finite"),
            (
                "sim_kin.nearest_vehicle",
                &self.sim_kin.nearest_vehicle,
                &distance,
                "a distance: finite, 0 to 3e7 m",
            ),
            (
                "log_kin.speed",
                &self.log_kin.speed,
                &not_negative,
                "a speed: finite, not negative",
            ),
            (
                "log_kin.angular_speed",
                &self.log_kin.angular_speed,
                &finite,
                "finite",
            ),
            ("log_kin.accel", &self.log_kin.accel, &finite, "finite"),
            (
                "log_kin.nearest_vehicle",
                &self.log_kin.nearest_vehicle,
                &distance,
                "a distance: finite, 0 to 3e7 m",
            ),
        ];
        for (name, values, ok, must) in series {
            if let Some((i, v)) = values.iter().enumerate().find(|(_, v)| !ok(**v)) {
                return Err(format!(
                    "{name}[{i}] is {}: must be {must}",
                    crate::geom::num(*v)
                ));
            }
        }
        // One figure per scene at most (none where a scene had no agent to score).
        for (name, n) in [
            ("ade", self.ade.len()),
            ("min_ade", self.min_ade.len()),
            ("collision", self.collision.len()),
            ("offroad", self.offroad.len()),
            ("scr", self.scr.len()),
            ("mmd_near", self.mmd_near.len()),
            ("mmd_edge", self.mmd_edge.len()),
        ] {
            if n > self.scenes {
                return Err(format!(
                    "{name} holds {n} figures: more than its {} scenes",
                    self.scenes
                ));
            }
        }
        for (a, b, x, y) in [
            ("ade", "fde", self.ade.len(), self.fde.len()),
            ("min_ade", "min_fde", self.min_ade.len(), self.min_fde.len()),
        ] {
            if x != y {
                return Err(format!(
                    "{a} holds {x} figures and {b} {y}: one of each per scene"
                ));
            }
        }
        if self.passed > self.achieved || self.achieved > self.checked {
            return Err(format!(
                "passed {}, achieved {}, checked {}: a sample passes only if it achieves the \
                 behaviour, and achieves it only if it was checked (passed <= achieved <= \
                 checked)",
                self.passed, self.achieved, self.checked
            ));
        }
        // One flag per agent of a sample at most, as `implausible` holds (collisions are
        // judged in the first sample or in each).
        if self.collided.len() > self.implausible.len() {
            return Err(format!(
                "collided holds {} flags: more than implausible's {} (one per agent of every \
                 sample)",
                self.collided.len(),
                self.implausible.len()
            ));
        }
        for (k, flags) in self.by_kind.iter().enumerate() {
            if flags.len() != self.implausible.len() {
                return Err(format!(
                    "by_kind[{k}] holds {} flags and implausible {}: one per judged agent",
                    flags.len(),
                    self.implausible.len()
                ));
            }
        }
        if !(self.seconds.is_finite() && self.seconds >= 0.0) {
            return Err(format!(
                "seconds is {}: must be finite, not negative",
                crate::geom::num(self.seconds)
            ));
        }
        Ok(())
    }

    /// Whether anything was scored for `task`: a conditional row needs an agent with a
    /// recorded future to compare with, a behaviour row a checked sample, an unconditional row
    /// an agent observed at a future step (a scene counted without one, such as rollouts that
    /// stop at the current step or hide every future state, printed a row of dashes and
    /// passed).
    pub fn scored(&self, task: Task) -> bool {
        match task {
            Task::Behaviour => self.checked > 0,
            Task::Conditional => !self.ade.is_empty(),
            Task::Unconditional => !self.scr.is_empty(),
        }
    }
}

/// The groups of a tally in print order: map kinds, then agent types across maps, then
/// types within each map kind.
pub fn group_order() -> Vec<Group> {
    let kinds = [MapKind::Highway, MapKind::Urban];
    let types = [
        AgentType::Vehicle,
        AgentType::Cyclist,
        AgentType::Pedestrian,
    ];
    let mut out: Vec<Group> = kinds
        .iter()
        .map(|m| Group {
            map: Some(*m),
            agent: None,
        })
        .collect();
    out.extend(types.iter().map(|t| Group {
        map: None,
        agent: Some(*t),
    }));
    for m in kinds {
        out.extend(types.iter().map(|t| Group {
            map: Some(m),
            agent: Some(*t),
        }));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::io::{load_scene, yaml, LoadOptions};
    use std::path::Path;

    fn scene(name: &str) -> Scene {
        let p = Path::new(env!("CARGO_MANIFEST_DIR"))
            .join("scripts/scenes")
            .join(name);
        load_scene(&p, 0, &LoadOptions::default()).unwrap()
    }

    #[test]
    fn a_junction_is_urban_and_a_straight_road_a_highway() {
        assert_eq!(map_kind(&scene("crossroads.yaml").map), MapKind::Urban);
        assert_eq!(map_kind(&scene("highway.yaml").map), MapKind::Highway);
        assert_eq!(
            map_kind(&scene("highway_cut_in.yaml").map),
            MapKind::Highway
        );
    }

    /// A two-lane road with a car and a cyclist beside it; the cyclist's sample `shift` metres
    /// sideways at every future step.
    fn car_and_cyclist() -> Scene {
        let text = "steps: 30\ncurrent_step: 5\nroad: {lanes: 2, length: 300}\nagents:\n  \
                    - {id: 1, s: 10, speed: 10}\n  - {id: 2, s: 10, lane: 1, speed: 5, type: cyclist}\n";
        yaml::parse(Path::new("t.yaml"), text).unwrap()
    }

    #[test]
    fn each_group_counts_only_its_agents_and_whole_scene_figures_stay_in_map_kinds() {
        let log = car_and_cyclist();
        let mut sim = log.clone();
        // The cyclist drifts 2 m sideways; the car keeps to its log.
        let c = sim.meta.current_step;
        let cyc = sim.agents.iter_mut().find(|a| a.id == 2).unwrap();
        for st in cyc.states.iter_mut().skip(c + 1) {
            st.y += 2.0;
        }
        let mut t = Tally::default();
        t.score(
            Task::Conditional,
            &log,
            std::slice::from_ref(&sim),
            None,
            None,
            &[],
        );
        let labels: Vec<&String> = t.groups.keys().collect();
        assert_eq!(
            labels,
            [
                "cyclists",
                "highway",
                "highway cyclists",
                "highway vehicles",
                "vehicles"
            ]
        );
        // Whole row: mean over the two agents (0 and 2 m); cyclists: 2 m; vehicles: 0.
        assert!((t.ade[0] - 1.0).abs() < 1e-9, "{:?}", t.ade);
        assert!((t.groups["cyclists"].ade[0] - 2.0).abs() < 1e-9);
        assert_eq!(t.groups["vehicles"].ade, vec![0.0]);
        assert_eq!(t.groups["highway"].ade, t.ade);
        // Off-road counts vehicles: the cyclists' row has none to count.
        assert!(t.groups["cyclists"].offroad.is_empty());
        assert_eq!(t.groups["vehicles"].offroad.len(), 1);
        // A cyclist's kinematics, and no nearest-vehicle distance among cyclists.
        let k = &t.groups["cyclists"].sim_kin;
        assert!(!k.speed.is_empty() && k.nearest_vehicle.is_empty());
        let mut u = Tally::default();
        u.score(
            Task::Unconditional,
            &log,
            std::slice::from_ref(&sim),
            None,
            None,
            &[],
        );
        assert_eq!(u.scr.len(), 1);
        assert_eq!(u.groups["highway"].scr.len(), 1);
        assert!(u.groups["cyclists"].scr.is_empty());
        // Collisions: the whole row counts vehicles, the cyclists' row its cyclist.
        assert_eq!(u.collided.iter().flatten().count(), 1);
        assert_eq!(u.groups["cyclists"].collided.iter().flatten().count(), 1);
    }

    #[test]
    fn absorbing_a_shard_merges_its_groups() {
        let log = car_and_cyclist();
        let mut a = Tally::default();
        a.score(
            Task::Conditional,
            &log,
            std::slice::from_ref(&log),
            None,
            None,
            &[],
        );
        let mut b = Tally::default();
        b.score(
            Task::Conditional,
            &scene("crossroads.yaml"),
            &[scene("crossroads.yaml")],
            None,
            None,
            &[],
        );
        a.absorb(b).unwrap();
        assert_eq!(a.scenes, 2);
        assert_eq!(a.groups["highway"].scenes, 1);
        assert_eq!(a.groups["urban"].scenes, 1);
        assert_eq!(a.groups["vehicles"].scenes, 2);
        assert_eq!(a.groups["cyclists"].scenes, 1);
        // Round trip through the JSON a shard writes.
        let back: Tally = serde_json::from_str(&serde_json::to_string(&a).unwrap()).unwrap();
        assert_eq!(back.groups["urban vehicles"].scenes, 1);
        assert_eq!(back.groups.len(), a.groups.len());
    }

    #[test]
    fn groups_print_map_kinds_then_types_then_both() {
        let labels: Vec<String> = group_order().iter().map(|g| g.label()).collect();
        assert_eq!(
            &labels[..5],
            ["highway", "urban", "vehicles", "cyclists", "pedestrians"]
        );
        assert_eq!(labels.len(), 2 + 3 + 6);
        assert_eq!(labels[5], "highway vehicles");
    }
}
