//! Agents and the series derived from their states.

use rhai::{Array, Dynamic, Engine};

use super::{doc, err, DocEntry, RResult, Shared};
use crate::cost::series::{Builder, Series};
use crate::cost::trajectory::Coord;
use crate::geom::wrap_angle;
use crate::scene::AgentType;

/// Hidden history elements kept in front of agent series (enough for jerk).
const HEAD: usize = 3;

/// Floor under speeds, m/s: keeps `speed` differentiable when an agent stands still.
const SPEED_EPS: f64 = 1e-3;

/// A script's handle on an agent.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct AgentRef {
    pub(crate) idx: usize,
    pub(crate) id: i64,
    /// Held ([`hold`]): its series carry no gradient, so terms about it move only the other
    /// agents.
    pub(crate) held: bool,
}

/// The coordinate series of agent `a`: hidden history constants, then the candidate future.
/// Headings are unwrapped so that differences are turn rates, not jumps of 2π.
pub(crate) fn coord_series(shared: &Shared, a: AgentRef, c: Coord) -> Series {
    let key = (a.idx, c as u8 + if a.held { 3 } else { 0 });
    if let Some(s) = shared.borrow().coords.get(&key) {
        return s.clone();
    }
    let s = build_coord_series(shared, a, c);
    shared.borrow_mut().coords.insert(key, s.clone());
    s
}

fn build_coord_series(shared: &Shared, agent: AgentRef, c: Coord) -> Series {
    let a = agent.idx;
    let ctx = shared.borrow();
    let scene = &ctx.scene;
    let cur = scene.meta.current_step;
    let lay = ctx.traj.layout;
    let dt = scene.meta.dt;
    let head = HEAD.min(cur + 1);
    let mut b = Builder::new(head + lay.steps, head, dt, dt);
    let mut prev: Option<f64> = None;
    let mut unwrap = |v: f64| {
        if c != Coord::Heading {
            return v;
        }
        let u = match prev {
            Some(p) => p + wrap_angle(v - p),
            None => v,
        };
        prev = Some(u);
        u
    };
    for k in cur + 1 - head..=cur {
        let s = scene.agents[a].states[k];
        let v = [s.x, s.y, s.heading][c as usize];
        let v = if s.valid { unwrap(v) } else { v };
        b.push_row(v, s.valid, std::iter::empty());
    }
    for t in 0..lay.steps {
        let (xyh, valid) = ctx.traj.state(a, t);
        let v = if valid { unwrap(xyh[c as usize]) } else { 0.0 };
        let var = (!agent.held).then(|| (lay.var(a, t, c), 1.0));
        b.push_row(v, valid, var);
    }
    b.build()
}

fn lift<T>(r: Result<T, String>) -> RResult<T> {
    r.or_else(|m| err(m))
}

/// Speed series (smoothly floored at [`SPEED_EPS`]).
pub(crate) fn speed(shared: &Shared, a: AgentRef) -> RResult<Series> {
    let vx = coord_series(shared, a, Coord::X).deriv();
    let vy = coord_series(shared, a, Coord::Y).deriv();
    lift(vx.zip(&vy, "speed", |x, y| {
        let r = (x * x + y * y + SPEED_EPS * SPEED_EPS).sqrt();
        Some((r, x / r, y / r))
    }))
}

/// Velocity along the heading (negative when reversing).
fn long_speed(shared: &Shared, a: AgentRef) -> RResult<Series> {
    let vx = coord_series(shared, a, Coord::X).deriv();
    let vy = coord_series(shared, a, Coord::Y).deriv();
    let h = coord_series(shared, a, Coord::Heading);
    let cos = lift(h.map("cos", |v| Some((v.cos(), -v.sin()))))?;
    let sin = lift(h.map("sin", |v| Some((v.sin(), v.cos()))))?;
    let mul = |x: f64, y: f64| Some((x * y, y, x));
    let a1 = lift(vx.zip(&cos, "long_speed", mul))?;
    let a2 = lift(vy.zip(&sin, "long_speed", mul))?;
    lift(a1.zip(&a2, "long_speed", |x, y| Some((x + y, 1.0, 1.0))))
}

fn history(shared: &Shared, a: usize, field: &str) -> RResult<Series> {
    let ctx = shared.borrow();
    let scene = &ctx.scene;
    let cur = scene.meta.current_step;
    let states = &scene.agents[a].states[..=cur];
    let dt = scene.meta.dt;
    let mut b = Builder::new(states.len(), 0, dt, -(cur as f64) * dt);
    for s in states {
        let v = match field {
            "x" => s.x,
            "y" => s.y,
            "heading" => s.heading,
            "speed" => s.speed(),
            _ => {
                return err(format!(
                    "history: field must be x, y, heading or speed, got {field:?}"
                ))
            }
        };
        b.push_row(v, s.valid, std::iter::empty());
    }
    Ok(b.build())
}

pub(crate) fn lookup(shared: &Shared, id: i64) -> RResult<AgentRef> {
    let mut ctx = shared.borrow_mut();
    match ctx.scene.agents.iter().position(|a| a.id == id) {
        Some(idx) => {
            if !ctx.named.contains(&id) {
                ctx.named.push(id);
            }
            Ok(AgentRef {
                idx,
                id,
                held: false,
            })
        }
        None => {
            let ids: Vec<String> = ctx
                .scene
                .agents
                .iter()
                .take(30)
                .map(|a| a.id.to_string())
                .collect();
            let more = if ctx.scene.agents.len() > 30 {
                ", ..."
            } else {
                ""
            };
            drop(ctx);
            let given = super::given_as(shared, &Dynamic::from(id));
            let from = if given.is_empty() {
                String::new()
            } else {
                format!(" ({})", given.join(" or "))
            };
            err(format!(
                "unknown agent id {id}{from}; the scene has agents {}{more}",
                ids.join(", ")
            ))
        }
    }
}

fn current(shared: &Shared, a: &AgentRef) -> RResult<crate::scene::AgentState> {
    let ctx = shared.borrow();
    let s = ctx.scene.agents[a.idx].states[ctx.scene.meta.current_step];
    if !s.valid {
        return err(format!(
            "agent {} is not observed at the current step",
            a.id
        ));
    }
    Ok(s)
}

pub(super) fn register(e: &mut Engine, shared: &Shared, docs: &mut Vec<DocEntry>) {
    const S: &str = "Agents";
    doc(
        docs,
        S,
        "agent(id) -> Agent",
        "The agent with this id; an unknown id is an error that lists the scene's ids.",
    );
    let sh = shared.clone();
    e.register_fn("agent", move |id: i64| lookup(&sh, id));
    // Anything else handed to agent(): `--param id=1.5` failed as "no function agent (f64)".
    let sh = shared.clone();
    e.register_fn("agent", move |v: Dynamic| -> RResult<AgentRef> {
        let given = super::given_as(&sh, &v);
        let from = if given.is_empty() {
            String::new()
        } else {
            format!(", from {}", given.join(" or "))
        };
        let shown = crate::io::name::shown(&v.to_string());
        let what = if v.is_float() {
            "a decimal number".to_string()
        } else if v.is_string() {
            "a word".to_string()
        } else if v.is_bool() {
            "true or false".to_string()
        } else {
            super::a_type(&v)
        };
        err(format!(
            "agent({shown}): an agent id is a whole number, not {what}{from}"
        ))
    });
    doc(
        docs,
        S,
        "agents() -> array of Agent",
        "Every agent of the scene, in scene order.",
    );
    let sh = shared.clone();
    e.register_fn("agents", move || {
        let ctx = sh.borrow();
        ctx.scene
            .agents
            .iter()
            .enumerate()
            .map(|(idx, a)| {
                Dynamic::from(AgentRef {
                    idx,
                    id: a.id,
                    held: false,
                })
            })
            .collect::<Array>()
    });
    doc(
        docs,
        S,
        "vehicles() -> array of Agent",
        "The vehicles of the scene.",
    );
    let sh = shared.clone();
    e.register_fn("vehicles", move || of_type(&sh, AgentType::Vehicle));
    doc(
        docs,
        S,
        "agents_of_type(t) -> array of Agent",
        "Agents of type \"vehicle\", \"pedestrian\", \"cyclist\" or \"other\".",
    );
    let sh = shared.clone();
    e.register_fn(
        "agents_of_type",
        move |t: &str| match AgentType::from_name(t) {
            Some(ty) => Ok(of_type(&sh, ty)),
            None => err(format!(
                "agents_of_type: unknown type {t:?} (vehicle, pedestrian, cyclist, other)"
            )),
        },
    );
    doc(
        docs,
        S,
        "ego() -> Agent",
        "The scene's ego / focal agent; an error when the format names none.",
    );
    let sh = shared.clone();
    e.register_fn("ego", move || {
        let ego = sh.borrow().scene.meta.ego;
        match ego {
            Some(id) => lookup(&sh, id),
            None => err("this scene names no ego agent; use agent(id)"),
        }
    });
    doc(
        docs,
        S,
        "hold(a) -> Agent, a.held -> bool",
        "The same agent held fixed: its series carry no gradient, so a term about it moves only the other agents (gap(a, hold(b), path) pushes a, never b back). Values are unchanged. Use it wherever a behaviour has one actor.",
    );
    e.register_fn("hold", |a: AgentRef| AgentRef { held: true, ..a });
    e.register_get("held", |a: &mut AgentRef| a.held);
    doc(
        docs,
        S,
        "a.present -> bool, a.has_future -> bool",
        "Whether the agent is observed at the current step (a.lane, a.lane_path() and the current_* values need it), and whether it has any future step in the candidate (first(), last() and the reductions of its series need one; an agent that appears later has none).",
    );
    let sh = shared.clone();
    e.register_get("present", move |a: &mut AgentRef| {
        let c = sh.borrow();
        c.scene.agents[a.idx].states[c.scene.meta.current_step].valid
    });
    let sh = shared.clone();
    e.register_get("has_future", move |a: &mut AgentRef| {
        let c = sh.borrow();
        let n = c.traj.layout.steps;
        c.traj.valid[a.idx * n..(a.idx + 1) * n].iter().any(|v| *v)
    });
    doc(
        docs,
        S,
        "allow(a, \"reverse\"), allow(a, \"collide\", b)",
        "Tells the sampler what the behaviour asks for that realism (on by default in simulate) would otherwise fight: `allow(a, \"reverse\")` lets `a` back up; `allow(a, \"collide\", b)` lets the boxes of `a` and `b` touch (an accident). These are the only exemptions; the other bounds of plausible driving, and keeping clear of every other agent, hold for every agent.",
    );
    let sh = shared.clone();
    e.register_fn("allow", move |a: AgentRef, what: &str| {
        match what {
            "reverse" => {}
            "collide" => {
                return err(
                    "allow: \"collide\" needs the other agent: allow(a, \"collide\", b)",
                )
            }
            _ => {
                return err(format!(
                    "allow: {what:?} cannot be allowed; only \"reverse\" and \"collide\" (the other bounds of plausible driving hold for every agent)"
                ))
            }
        }
        let mut c = sh.borrow_mut();
        if !c.may_reverse.contains(&a.idx) {
            c.may_reverse.push(a.idx);
        }
        Ok(())
    });
    let sh = shared.clone();
    e.register_fn("allow", move |a: AgentRef, what: &str, b: AgentRef| {
        if what != "collide" {
            return err(format!(
                "allow: {what:?} with a second agent cannot be allowed; only allow(a, \"collide\", b)"
            ));
        }
        if a.idx == b.idx {
            return err(format!(
                "allow: an agent cannot collide with itself (both arguments are agent {})",
                a.id
            ));
        }
        let pair = (a.idx.min(b.idx), a.idx.max(b.idx));
        let mut c = sh.borrow_mut();
        if !c.may_collide.contains(&pair) {
            c.may_collide.push(pair);
        }
        Ok(())
    });
    doc(
        docs,
        S,
        "a.id -> int, a.type -> string, a.length -> float, a.width -> float",
        "Identity and footprint.",
    );
    e.register_get("id", |a: &mut AgentRef| a.id);
    let sh = shared.clone();
    e.register_get("type", move |a: &mut AgentRef| {
        sh.borrow().scene.agents[a.idx]
            .agent_type
            .name()
            .to_string()
    });
    let sh = shared.clone();
    e.register_get("length", move |a: &mut AgentRef| {
        sh.borrow().scene.agents[a.idx].length
    });
    let sh = shared.clone();
    e.register_get("width", move |a: &mut AgentRef| {
        sh.borrow().scene.agents[a.idx].width
    });

    doc(docs, S, "a.x, a.y, a.heading -> Series", "Position and heading over the future steps (heading unwrapped, so it is continuous); these carry the gradient.");
    let sh = shared.clone();
    e.register_get("x", move |a: &mut AgentRef| coord_series(&sh, *a, Coord::X));
    let sh = shared.clone();
    e.register_get("y", move |a: &mut AgentRef| coord_series(&sh, *a, Coord::Y));
    let sh = shared.clone();
    e.register_get("heading", move |a: &mut AgentRef| {
        coord_series(&sh, *a, Coord::Heading)
    });
    doc(docs, S, "a.vx, a.vy -> Series", "Velocity components, m/s.");
    let sh = shared.clone();
    e.register_get("vx", move |a: &mut AgentRef| {
        coord_series(&sh, *a, Coord::X).deriv()
    });
    let sh = shared.clone();
    e.register_get("vy", move |a: &mut AgentRef| {
        coord_series(&sh, *a, Coord::Y).deriv()
    });
    doc(
        docs,
        S,
        "a.speed -> Series",
        "Speed, m/s (never below 0.001, so that it stays differentiable at rest).",
    );
    let sh = shared.clone();
    e.register_get("speed", move |a: &mut AgentRef| speed(&sh, *a));
    doc(
        docs,
        S,
        "a.long_speed -> Series",
        "Velocity along the heading, m/s: negative when driving in reverse.",
    );
    let sh = shared.clone();
    e.register_get("long_speed", move |a: &mut AgentRef| long_speed(&sh, *a));
    doc(
        docs,
        S,
        "a.accel -> Series",
        "Rate of change of speed, m/s².",
    );
    let sh = shared.clone();
    e.register_get("accel", move |a: &mut AgentRef| {
        Ok::<_, Box<rhai::EvalAltResult>>(speed(&sh, *a)?.deriv())
    });
    doc(
        docs,
        S,
        "a.jerk -> Series",
        "Rate of change of acceleration, m/s³.",
    );
    let sh = shared.clone();
    e.register_get("jerk", move |a: &mut AgentRef| {
        Ok::<_, Box<rhai::EvalAltResult>>(speed(&sh, *a)?.deriv().deriv())
    });
    doc(
        docs,
        S,
        "a.yaw_rate -> Series",
        "Heading change per second, rad/s.",
    );
    let sh = shared.clone();
    e.register_get("yaw_rate", move |a: &mut AgentRef| {
        coord_series(&sh, *a, Coord::Heading).deriv()
    });

    doc(
        docs,
        S,
        "a.current_x, a.current_y, a.current_heading, a.current_speed -> float",
        "The recorded state at the current step (constants).",
    );
    let sh = shared.clone();
    e.register_get("current_x", move |a: &mut AgentRef| {
        current(&sh, a).map(|s| s.x)
    });
    let sh = shared.clone();
    e.register_get("current_y", move |a: &mut AgentRef| {
        current(&sh, a).map(|s| s.y)
    });
    let sh = shared.clone();
    e.register_get("current_heading", move |a: &mut AgentRef| {
        current(&sh, a).map(|s| s.heading)
    });
    let sh = shared.clone();
    e.register_get("current_speed", move |a: &mut AgentRef| {
        current(&sh, a).map(|s| s.speed())
    });
    doc(docs, S, "a.history(field) -> Series", "Recorded \"x\", \"y\", \"heading\" or \"speed\" from the first step to the current one (constants; at_time takes negative times).");
    let sh = shared.clone();
    e.register_fn("history", move |a: &mut AgentRef, f: &str| {
        history(&sh, a.idx, f)
    });
    doc(
        docs,
        S,
        "times() -> Series",
        "Seconds after the current step of every future step (a constant series: 1·DT, 2·DT, ...).",
    );
    let sh = shared.clone();
    e.register_fn("times", move || {
        let ctx = sh.borrow();
        let dt = ctx.scene.meta.dt;
        let t: Vec<f64> = (1..=ctx.traj.layout.steps).map(|k| k as f64 * dt).collect();
        Series::constant(&t, dt, dt)
    });
    e.register_fn("to_string", |a: &mut AgentRef| format!("agent {}", a.id));
    e.register_fn("to_debug", |a: &mut AgentRef| format!("Agent({})", a.id));
}

fn of_type(shared: &Shared, t: AgentType) -> Array {
    let ctx = shared.borrow();
    ctx.scene
        .agents
        .iter()
        .enumerate()
        .filter(|(_, a)| a.agent_type == t)
        .map(|(idx, a)| {
            Dynamic::from(AgentRef {
                idx,
                id: a.id,
                held: false,
            })
        })
        .collect()
}
