//! The bounds of plausible motion per road-user type: what a car (a cyclist, a pedestrian)
//! can do. The kinematic judge ([`crate::eval::kinematic`]) flags motion beyond them; realism
//! ([`crate::cost::Realism`]) and the sampler keep guided samples within them.

use super::AgentType;

/// The bounds of plausible vehicle motion.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct KinematicLimits {
    /// Shortest span of the centred differences, seconds.
    pub window: f64,
    /// Speed along the heading below which a vehicle reverses, m/s (negative).
    pub reverse_speed: f64,
    /// Speed above which a vehicle sprints whatever its current speed, m/s.
    pub max_speed: f64,
    /// A vehicle sprints above `sprint_factor` × its current speed + `sprint_margin`.
    pub sprint_factor: f64,
    /// See `sprint_factor`, m/s.
    pub sprint_margin: f64,
    /// Seconds after the current step from which the sprint bound grows ([`Self::sprint_bound`]).
    pub sprint_after: f64,
    /// How fast the sprint bound grows after `sprint_after`, m/s per second.
    pub sprint_accel: f64,
    /// Largest plausible longitudinal acceleration or deceleration, m/s².
    pub max_accel: f64,
    /// Largest plausible lateral acceleration, m/s².
    pub max_lateral: f64,
    /// Largest plausible angle between velocity and heading axis, radians.
    pub max_crab: f64,
    /// Largest plausible path curvature, 1/m (Waymax's steering bound).
    pub max_curvature: f64,
    /// Speed above which swerves, crabbing and curvature are judged, m/s (below it the
    /// direction of a few centimetres of tracking noise means nothing).
    pub moving: f64,
    /// Span of each of the two windows whose speeds give the acceleration at the joint of
    /// history and future and at the end of a track, seconds.
    pub joint_window: f64,
}

impl KinematicLimits {
    /// The bounds for a road user of type `t`, these being a car's: a cyclist's are lower
    /// (15 m/s, 5 m/s², a 2 m turning radius; the simulated cyclists of the urban corpora reach
    /// 11.4 m/s and 4.1 m/s² over 0.6 s), a pedestrian's lower still and without a heading to
    /// reverse, crab or steer against (people step any way they face). `None` for objects of
    /// unknown type.
    pub fn for_type(&self, t: AgentType) -> Option<KinematicLimits> {
        match t {
            AgentType::Vehicle => Some(*self),
            AgentType::Cyclist => Some(KinematicLimits {
                max_speed: 15.0,
                sprint_margin: 4.0,
                sprint_accel: 1.5,
                max_accel: 5.0,
                max_lateral: 4.0,
                max_curvature: 0.5,
                moving: 2.0,
                ..*self
            }),
            AgentType::Pedestrian => Some(KinematicLimits {
                reverse_speed: f64::NEG_INFINITY,
                max_speed: 5.0,
                sprint_factor: 1.6,
                sprint_margin: 3.0,
                sprint_accel: 0.5,
                max_accel: 4.0,
                max_lateral: 4.0,
                max_crab: std::f64::consts::FRAC_PI_2,
                max_curvature: f64::INFINITY,
                moving: 1.0,
                ..*self
            }),
            AgentType::Other => None,
        }
    }

    /// The speed above which a road user that was at `v0` m/s at the current step sprints, `tau`
    /// seconds later. `sprint_factor · v0 + sprint_margin` was set on 4 s futures; over longer
    /// ones a car keeps speeding up as a brisk driver does, so beyond `sprint_after` the bound
    /// grows by `sprint_accel` a second (at 8 s the fixed bound flagged 6 % of WOMD's recorded
    /// vehicles and half its cyclists). `max_speed` caps it whenever.
    pub fn sprint_bound(&self, v0: f64, tau: f64) -> f64 {
        let late = self.sprint_accel * (tau - self.sprint_after).max(0.0);
        self.max_speed
            .min(self.sprint_factor * v0 + self.sprint_margin + late)
    }

    /// Steps of each [`KinematicLimits::joint_window`] at step length `dt`.
    pub fn joint_steps(&self, dt: f64) -> usize {
        ((self.joint_window / dt) - 1e-9).ceil().max(1.0) as usize
    }
}

impl Default for KinematicLimits {
    fn default() -> Self {
        Self {
            window: 0.5,
            reverse_speed: -1.0,
            max_speed: 40.0,
            sprint_factor: 1.6,
            sprint_margin: 8.0,
            sprint_after: 4.0,
            sprint_accel: 3.0,
            max_accel: 7.0,
            max_lateral: 5.0,
            max_crab: 35f64.to_radians(),
            max_curvature: 0.3,
            moving: 3.0,
            joint_window: 0.3,
        }
    }
}
