//! Numbers in the JSON drivescript writes, where JSON has none.
//!
//! JSON has no NaN or infinity, and serde_json writes them as `null`: in a report a missing
//! value, a NaN and an infinite distance then read alike (a verdict's
//! `end_offset_from_centre` of a car that ends on no lane was `null`). The fields below that
//! can hold them are written through these functions instead: a finite number as a number,
//! anything else as the string `"NaN"`, `"inf"` or `"-inf"` under its own key, so that a
//! reader sees what the value was and where it came from.

use std::collections::BTreeMap;

use serde::ser::{SerializeMap, Serializer};

/// `x` as a JSON value: a number when finite, else `"NaN"`, `"inf"` or `"-inf"`.
pub fn number(x: f64) -> serde_json::Value {
    match serde_json::Number::from_f64(x) {
        Some(n) => serde_json::Value::Number(n),
        None => serde_json::Value::String(word(x).into()),
    }
}

/// What a non-finite number is called in the JSON drivescript writes.
pub fn word(x: f64) -> &'static str {
    if x.is_nan() {
        "NaN"
    } else if x > 0.0 {
        "inf"
    } else {
        "-inf"
    }
}

/// Serialises an `f64` field as [`number`] writes it (`#[serde(serialize_with = ...)]`).
pub fn f64_explicit<S: Serializer>(x: &f64, s: S) -> Result<S::Ok, S::Error> {
    if x.is_finite() {
        s.serialize_f64(*x)
    } else {
        s.serialize_str(word(*x))
    }
}

/// Serialises an `Option<f64>` field: `None` as `null` (no value), a value as [`f64_explicit`].
pub fn opt_f64_explicit<S: Serializer>(x: &Option<f64>, s: S) -> Result<S::Ok, S::Error> {
    match x {
        None => s.serialize_none(),
        Some(v) => f64_explicit(v, s),
    }
}

/// Serialises a map of numbers with each value as [`f64_explicit`] writes it.
pub fn map_f64_explicit<S: Serializer>(m: &BTreeMap<String, f64>, s: S) -> Result<S::Ok, S::Error> {
    struct Explicit(f64);
    impl serde::Serialize for Explicit {
        fn serialize<S: Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
            f64_explicit(&self.0, s)
        }
    }
    let mut map = s.serialize_map(Some(m.len()))?;
    for (k, v) in m {
        map.serialize_entry(k, &Explicit(*v))?;
    }
    map.end()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(serde::Serialize)]
    struct Row {
        #[serde(serialize_with = "f64_explicit")]
        a: f64,
        #[serde(serialize_with = "opt_f64_explicit")]
        b: Option<f64>,
        #[serde(serialize_with = "map_f64_explicit")]
        m: BTreeMap<String, f64>,
    }

    #[test]
    fn non_finite_numbers_are_named_not_null() {
        let m = BTreeMap::from([
            ("gap".to_string(), f64::INFINITY),
            ("speed".to_string(), 2.5),
            ("x".to_string(), f64::NAN),
        ]);
        let row = Row {
            a: f64::NEG_INFINITY,
            b: Some(f64::NAN),
            m,
        };
        let v = serde_json::to_value(&row).unwrap();
        assert_eq!(
            v,
            serde_json::json!({"a": "-inf", "b": "NaN", "m": {"gap": "inf", "speed": 2.5, "x": "NaN"}})
        );
        // Plain serde_json would have written every one of them as null.
        assert_eq!(serde_json::json!(f64::NAN), serde_json::Value::Null);
        let none = Row {
            a: 1.0,
            b: None,
            m: BTreeMap::new(),
        };
        assert_eq!(
            serde_json::to_value(&none).unwrap()["b"],
            serde_json::Value::Null
        );
        assert_eq!(number(0.5), serde_json::json!(0.5));
        assert_eq!(number(f64::INFINITY), serde_json::json!("inf"));
    }
}
