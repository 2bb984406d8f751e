//! Parameters: the one name → value map shared by cost scripts (constants), behaviour checkers
//! (agent roles, limits) and the command line (`--param cutter=1 victim=2`).

use std::fmt;

use serde::ser::{Serialize, SerializeMap, Serializer};

use super::engine::CostError;

/// Named parameters in the order given. A script sees them as constants; a checker reads its
/// roles and limits from them ([`Params::number`]).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Params(pub Vec<(String, ParamValue)>);

/// A parameter's value.
#[derive(Debug, Clone, PartialEq)]
pub enum ParamValue {
    /// An integer (agent and lane ids).
    Int(i64),
    /// A number.
    Float(f64),
    /// A boolean.
    Bool(bool),
    /// Anything else.
    Str(String),
}

impl ParamValue {
    /// The value as a number, when it is one.
    pub fn as_f64(&self) -> Option<f64> {
        match self {
            ParamValue::Int(i) => Some(*i as f64),
            ParamValue::Float(f) => Some(*f),
            _ => None,
        }
    }

    /// A number as a parameter: whole numbers (agent ids) become integers, which `agent(...)`
    /// needs, the rest floats.
    pub fn number(v: f64) -> Self {
        if v.fract() == 0.0 && v.abs() < 9.0e15 {
            ParamValue::Int(v as i64)
        } else {
            ParamValue::Float(v)
        }
    }
}

impl fmt::Display for ParamValue {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            ParamValue::Int(i) => write!(f, "{i}"),
            // `{:?}` keeps the point (1.0, not 1), so the value parses back as a float.
            ParamValue::Float(x) => write!(f, "{x:?}"),
            ParamValue::Bool(b) => write!(f, "{b}"),
            ParamValue::Str(s) => write!(f, "{s}"),
        }
    }
}

impl Serialize for ParamValue {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        match self {
            ParamValue::Int(i) => s.serialize_i64(*i),
            ParamValue::Float(x) => s.serialize_f64(*x),
            ParamValue::Bool(b) => s.serialize_bool(*b),
            ParamValue::Str(v) => s.serialize_str(v),
        }
    }
}

/// A map in the given order: `{"cutter": 401, "victim": 399}`.
impl Serialize for Params {
    fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        let mut m = s.serialize_map(Some(self.0.len()))?;
        for (k, v) in &self.0 {
            m.serialize_entry(k, v)?;
        }
        m.end()
    }
}

impl Params {
    /// Parameters from a JSON (or YAML, through serde) object of scalars, by name:
    /// integers stay integers (agent ids), other numbers are floats. Anything else
    /// (arrays, objects, null) is an error naming the key.
    pub fn from_json(v: &serde_json::Value) -> Result<Self, String> {
        let obj = v
            .as_object()
            .ok_or_else(|| format!("parameters must be a map of name: value, not {v}"))?;
        let mut p = Params::default();
        for (k, v) in obj {
            let value = match v {
                serde_json::Value::Number(n) => match n.as_i64() {
                    Some(i) => ParamValue::Int(i),
                    None => ParamValue::Float(n.as_f64().unwrap_or(f64::NAN)),
                },
                serde_json::Value::Bool(b) => ParamValue::Bool(*b),
                serde_json::Value::String(s) => ParamValue::Str(s.clone()),
                other => {
                    let other = crate::io::name::shown(&other.to_string());
                    return Err(format!(
                        "parameter \"{}\": {other} is not a number, boolean or string",
                        crate::io::name::shown(k)
                    ));
                }
            };
            p.push_checked(k, value)
                .map_err(|m| format!("parameter \"{}\": {m}", crate::io::name::shown(k)))?;
        }
        Ok(p)
    }

    /// Adds `name` = `value`, checked as every source of parameters is (the command line, a
    /// batch file, the Python binding): the name an identifier, not given before; a string
    /// short and printable; a number finite (a NaN limit compares false with everything, so a
    /// script or checker reading it would pass whatever the trajectories do). The error is
    /// the reason alone, for the caller to name the parameter.
    pub fn push_checked(&mut self, name: &str, value: ParamValue) -> Result<(), String> {
        check_name(name)?;
        if self.get(name).is_some() {
            return Err("given twice".into());
        }
        match &value {
            ParamValue::Str(s) => check_value(s)?,
            ParamValue::Float(f) if !f.is_finite() => {
                return Err(format!("{} is not finite", crate::geom::num(*f)));
            }
            _ => {}
        }
        self.0.push((name.to_string(), value));
        Ok(())
    }
}

/// The longest parameter name, characters.
pub const MAX_NAME_CHARS: usize = 64;
/// The longest parameter value, characters: ids, numbers and words (`left`) are short, and a
/// value is quoted back in errors.
pub const MAX_VALUE_CHARS: usize = 256;

/// A parameter's name is an identifier (a script sees it as a constant).
fn check_name(k: &str) -> Result<(), String> {
    if k.chars().count() > MAX_NAME_CHARS {
        return Err(format!("a name is at most {MAX_NAME_CHARS} characters"));
    }
    let ident = k
        .chars()
        .next()
        .is_some_and(|c| c.is_ascii_alphabetic() || c == '_')
        && k.chars().all(|c| c.is_ascii_alphanumeric() || c == '_');
    if !ident {
        return Err("not a valid identifier".into());
    }
    Ok(())
}

/// A value is something to read back: not empty, not an essay, nothing that rewrites the
/// terminal it is quoted on.
fn check_value(v: &str) -> Result<(), String> {
    if v.is_empty() {
        return Err(
            "no value after `=`: give name=VALUE (a number, true or false, or a word)".into(),
        );
    }
    let n = v.chars().count();
    if n > MAX_VALUE_CHARS {
        return Err(format!(
            "a value of {n} characters (\"{}\"): at most {MAX_VALUE_CHARS}",
            crate::io::name::shown(v)
        ));
    }
    if let Err(bad) = crate::io::name::check_name(v) {
        return Err(format!(
            "the value \"{}\" contains {bad}",
            crate::io::name::shown(v)
        ));
    }
    Ok(())
}

/// `cutter=401 victim=399`, the form `--param` reads.
impl fmt::Display for Params {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        for (i, (k, v)) in self.0.iter().enumerate() {
            if i > 0 {
                f.write_str(" ")?;
            }
            write!(f, "{k}={v}")?;
        }
        Ok(())
    }
}

impl Params {
    /// Parses `name=value` arguments: integers, floats and booleans are typed, the rest strings.
    /// A name given twice is an error.
    pub fn parse<S: AsRef<str>>(args: &[S]) -> Result<Self, CostError> {
        let mut out = Params::default();
        for a in args {
            let a = a.as_ref();
            let Some((k, v)) = a.split_once('=') else {
                return Err(CostError::Param {
                    name: crate::io::name::shown(a),
                    message: "expected name=value".into(),
                });
            };
            let k = k.trim();
            let bad = |message: String| CostError::Param {
                name: crate::io::name::shown(k),
                message,
            };
            check_name(k).map_err(bad)?;
            let v = v.trim();
            check_value(v).map_err(bad)?;
            let digits = v.strip_prefix(['-', '+']).unwrap_or(v);
            let val = if let Ok(i) = v.parse::<i64>() {
                ParamValue::Int(i)
            } else if !digits.is_empty() && digits.bytes().all(|b| b.is_ascii_digit()) {
                // Read as a float, `cutter=9223372036854775808` reached the script as
                // 9.223372036854776e18 and was refused as "not a decimal number", a value
                // nobody wrote.
                return Err(bad(format!(
                    "{v} is a whole number beyond ±{}, which no parameter holds (write it with a \
                     decimal point or an exponent if a real number is meant)",
                    i64::MAX
                )));
            } else if let Ok(f) = v.parse::<f64>() {
                if crate::geom::written_beyond_f64(v, f) {
                    return Err(bad(format!("{v} {}", crate::geom::BEYOND_F64)));
                }
                ParamValue::Float(f)
            } else if v == "true" || v == "false" {
                ParamValue::Bool(v == "true")
            } else {
                ParamValue::Str(v.to_string())
            };
            out.push_checked(k, val).map_err(bad)?;
        }
        Ok(out)
    }

    /// Numbers by name, whole numbers as integers ([`ParamValue::number`]).
    pub fn numbers<K: AsRef<str>>(kv: &[(K, f64)]) -> Self {
        Params(
            kv.iter()
                .map(|(k, v)| (k.as_ref().to_string(), ParamValue::number(*v)))
                .collect(),
        )
    }

    /// The value named `name`.
    pub fn get(&self, name: &str) -> Option<&ParamValue> {
        self.0.iter().find(|(k, _)| k == name).map(|(_, v)| v)
    }

    /// The value named `name` as a number (`None` when absent or not a number).
    pub fn number(&self, name: &str) -> Option<f64> {
        self.get(name).and_then(ParamValue::as_f64)
    }

    /// Sets `name`, replacing an earlier value in place.
    pub fn set(&mut self, name: &str, value: ParamValue) {
        match self.0.iter_mut().find(|(k, _)| k == name) {
            Some(slot) => slot.1 = value,
            None => self.0.push((name.to_string(), value)),
        }
    }

    /// These parameters with `over`'s values set on top (explicit `--param` values over
    /// suggested ones).
    pub fn overridden_by(&self, over: &Params) -> Params {
        let mut out = self.clone();
        for (k, v) in &over.0 {
            out.set(k, v.clone());
        }
        out
    }

    /// Names in order.
    pub fn names(&self) -> impl Iterator<Item = &str> {
        self.0.iter().map(|(k, _)| k.as_str())
    }

    /// Whether there are none.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_types_values_and_round_trips_through_display() {
        let p = Params::parse(&["a=3", "b=2.5", "c=true", "d=left", "e=-1e3"]).unwrap();
        assert_eq!(p.get("a"), Some(&ParamValue::Int(3)));
        assert_eq!(p.get("b"), Some(&ParamValue::Float(2.5)));
        assert_eq!(p.get("c"), Some(&ParamValue::Bool(true)));
        assert_eq!(p.get("d"), Some(&ParamValue::Str("left".into())));
        assert_eq!(p.number("e"), Some(-1000.0));
        assert_eq!(p.number("d"), None);
        assert_eq!(p.to_string(), "a=3 b=2.5 c=true d=left e=-1000.0");
        let again: Vec<String> = p.to_string().split(' ').map(String::from).collect();
        assert_eq!(Params::parse(&again).unwrap(), p);
    }

    #[test]
    fn parse_rejects_bad_arguments() {
        for (args, want) in [
            (vec!["a"], "expected name=value"),
            (vec!["1a=2"], "not a valid identifier"),
            (vec!["a=1", "a=2"], "given twice"),
            (vec!["a=inf"], "not finite"),
            (vec!["a=NaN"], "not finite"),
            // Said as written, not as "inf is not finite" (issue 32).
            (
                vec!["gap=-1e400"],
                "parameter \"gap\": -1e400 is beyond the largest number",
            ),
            (
                vec!["cutter=9223372036854775808"],
                "parameter \"cutter\": 9223372036854775808 is a whole number beyond ±9223372036854775807",
            ),
            (vec!["cutter=-99999999999999999999"], "is a whole number beyond"),
            (vec!["gap="], "parameter \"gap\": no value after `=`"),
            (vec!["gap= "], "parameter \"gap\": no value after `=`"),
            (vec!["turn=le\u{1b}[2Jft"], "the control character U+001B"),
            (vec!["turn=le\u{202E}ft"], "the invisible character U+202E"),
        ] {
            let e = Params::parse(&args).unwrap_err().to_string();
            assert!(e.contains(want), "{args:?}: {e}");
        }
        // A 100 KB value or name is refused in a message of a line, naming the parameter.
        let huge = format!("gap={}", "9".repeat(100_000));
        let e = Params::parse(&[huge]).unwrap_err().to_string();
        assert!(
            e.starts_with("parameter \"gap\": a value of 100000 characters (\"999")
                && e.ends_with("…\"): at most 256")
                && e.len() < 200,
            "{e}"
        );
        let e = Params::parse(&[format!("{}=1", "n".repeat(100_000))])
            .unwrap_err()
            .to_string();
        assert!(e.contains("at most 64 characters") && e.len() < 200, "{e}");
    }

    #[test]
    fn json_parameters_are_checked_as_command_line_ones() {
        let e = Params::from_json(&serde_json::json!({"turn": "a\nerror: b"})).unwrap_err();
        assert!(e.contains("the control character U+000A"), "{e}");
        let e = Params::from_json(&serde_json::json!({"a b": 1})).unwrap_err();
        assert!(e.contains("not a valid identifier"), "{e}");
        let e = Params::from_json(&serde_json::json!({"v": "x".repeat(300)})).unwrap_err();
        assert!(
            e.contains("a value of 300 characters") && e.len() < 200,
            "{e}"
        );
    }

    #[test]
    fn numbers_make_ids_integers_and_overrides_replace_in_place() {
        let p = Params::numbers(&[("cutter", 401.0), ("gap", 2.5)]);
        assert_eq!(p.get("cutter"), Some(&ParamValue::Int(401)));
        assert_eq!(p.get("gap"), Some(&ParamValue::Float(2.5)));
        let q = p.overridden_by(&Params::parse(&["cutter=7", "extra=1"]).unwrap());
        assert_eq!(q.to_string(), "cutter=7 gap=2.5 extra=1");
        assert_eq!(
            serde_json::to_string(&q).unwrap(),
            r#"{"cutter":7,"gap":2.5,"extra":1}"#
        );
    }
}
