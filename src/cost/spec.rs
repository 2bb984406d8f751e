//! A cost script before it meets a scene: source, name, parameters and limits. Everything that
//! compiles scripts against scenes it chooses itself (closed loop, [`super::BoundScript`], the
//! Python package) starts from one.

use std::path::Path;
use std::rc::Rc;

use super::engine::{check_params, read_script, CostError, CostScript, Limits};
use super::params::Params;
use crate::scene::Scene;

/// A cost script's source, name, parameters and limits: everything needed to compile it.
#[derive(Debug, Clone)]
pub struct ScriptSpec {
    /// Source text.
    pub source: String,
    /// Name used in messages.
    pub name: String,
    /// Parameters.
    pub params: Params,
    /// Resource limits, the same at every compilation.
    pub limits: Limits,
}

impl ScriptSpec {
    /// A script with default limits.
    pub fn new(source: impl Into<String>, name: impl Into<String>, params: Params) -> Self {
        Self {
            source: source.into(),
            name: name.into(),
            params,
            limits: Limits::default(),
        }
    }

    /// The script in file `path` ([`read_script`]'s rules), named by the path as `drivescript
    /// cost --script` names it, with default limits; the parameters are checked against the
    /// source ([`check_params`]) so that a misspelt one is said before any scene is read.
    pub fn from_file(path: &Path, params: Params) -> Result<Self, CostError> {
        let spec = Self::new(read_script(path)?, path.display().to_string(), params);
        check_params(&[&spec.source], &spec.params)?;
        Ok(spec)
    }

    /// Compiles the script without a scene ([`CostScript::check_syntax`]): a run over many
    /// scenes checks its scripts once, before the first.
    pub fn check_syntax(&self) -> Result<(), CostError> {
        CostScript::check_syntax(&self.source, &self.name, &self.limits)
    }

    /// Compiles the script against `scene`.
    pub fn compile(&self, scene: Rc<Scene>) -> Result<CostScript, CostError> {
        CostScript::compile(&self.source, &self.name, scene, &self.params, &self.limits)
    }
}
