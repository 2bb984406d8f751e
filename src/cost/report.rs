//! What an evaluation returns: per-term values and gradients, and their weighted total.

use std::time::Duration;

use serde::Serialize;

use super::dual::Grad;
use super::trajectory::VarLayout;

/// One term of an evaluation.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct TermReport {
    /// Name given in the script.
    pub name: String,
    /// Weight given in the script.
    pub weight: f64,
    /// Unweighted value.
    pub value: f64,
    /// Line of the `term(...)` call.
    pub line: usize,
    /// The value at or below which the term counts as met, when the script says
    /// (`term(name, value, weight, tolerance)`); the LLM loop's acceptance uses it.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub tolerance: Option<f64>,
    /// Sparse gradient of the unweighted value.
    #[serde(skip)]
    pub grad: Grad,
}

impl TermReport {
    /// Euclidean norm of the gradient.
    pub fn grad_norm(&self) -> f64 {
        self.grad.iter().map(|(_, g)| g * g).sum::<f64>().sqrt()
    }
}

/// Values and gradients of all terms on one candidate.
#[derive(Debug, Clone, PartialEq)]
pub struct CostReport {
    /// Terms in declaration order.
    pub terms: Vec<TermReport>,
    /// Weighted sum of the terms.
    pub total: f64,
    /// Dense gradient of the total w.r.t. every coordinate of the layout.
    pub gradient: Vec<f64>,
    /// The coordinate layout.
    pub layout: VarLayout,
    /// What the script printed.
    pub prints: Vec<String>,
    /// Time taken by the evaluation.
    pub elapsed: Duration,
    /// Agents (scene indices) the script allows to reverse (`allow(a, "reverse")`), which
    /// realism then does not hold back ([`super::Realism`]).
    pub may_reverse: Vec<usize>,
    /// Pairs of agents (scene indices, smaller first) the script allows to touch
    /// (`allow(a, "collide", b)`), which realism then does not hold apart.
    pub may_collide: Vec<(usize, usize)>,
    /// Agent ids the script named with `agent(id)`, in first-lookup order.
    pub named: Vec<i64>,
}

impl CostReport {
    pub(crate) fn new(
        terms: Vec<TermReport>,
        layout: VarLayout,
        prints: Vec<String>,
        elapsed: Duration,
    ) -> Self {
        let mut gradient = vec![0.0; layout.len()];
        let mut total = 0.0;
        for t in &terms {
            total += t.weight * t.value;
            for &(k, g) in &t.grad {
                gradient[k as usize] += t.weight * g;
            }
        }
        Self {
            terms,
            total,
            gradient,
            layout,
            prints,
            elapsed,
            may_reverse: Vec::new(),
            may_collide: Vec::new(),
            named: Vec::new(),
        }
    }

    /// This report, made on [`Trajectories::spliced`](super::Trajectories::spliced)
    /// trajectories, with its gradients moved to the layout `to` of the part spliced in at
    /// step `done`: a coordinate at step `j ≥ done` becomes step `j − done`, and the executed
    /// steps before `done`, which nothing can move any more, drop out. Values and total stay
    /// those of the whole horizon.
    pub fn shifted(self, done: usize, to: VarLayout) -> Self {
        let from = self.layout;
        let terms = self
            .terms
            .into_iter()
            .map(|mut t| {
                t.grad = t
                    .grad
                    .iter()
                    .filter_map(|&(v, g)| {
                        let (a, j, c) = from.decode(v);
                        (j >= done && j - done < to.steps).then(|| (to.var(a, j - done, c), g))
                    })
                    .collect();
                t
            })
            .collect();
        let mut out = Self::new(terms, to, self.prints, self.elapsed);
        out.may_reverse = self.may_reverse;
        out.may_collide = self.may_collide;
        out.named = self.named;
        out
    }

    /// The term with this name.
    pub fn term(&self, name: &str) -> Option<&TermReport> {
        self.terms.iter().find(|t| t.name == name)
    }

    /// Norm of the total's gradient restricted to each agent's coordinates (scene order).
    pub fn agent_grad_norms(&self) -> Vec<f64> {
        let per = self.layout.steps * 3;
        (0..self.layout.agents)
            .map(|a| {
                self.gradient[a * per..(a + 1) * per]
                    .iter()
                    .map(|g| g * g)
                    .sum::<f64>()
                    .sqrt()
            })
            .collect()
    }
}
