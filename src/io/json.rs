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

/// `text` parsed as JSON, refusing an object that names a key twice: `{"choices": [A],
/// "choices": [B]}` (or a message with two `content`s) was read as its last copy without a
/// word, though a reply holding two answers is no answer (and another reader, or a proxy
/// between, takes the first). Scene, rollout and checkpoint files refuse the same; here for
/// the readers of every stage (LLM replies and runs, AV2 maps, checkpoint headers,
/// evaluations).
pub(crate) fn parse_json(text: &str) -> serde_json::Result<serde_json::Value> {
    use serde::de::{DeserializeSeed, Deserializer, Error, MapAccess, SeqAccess, Visitor};
    use serde_json::Value;
    struct Unique;
    impl<'de> DeserializeSeed<'de> for Unique {
        type Value = Value;
        fn deserialize<D: Deserializer<'de>>(self, d: D) -> Result<Value, D::Error> {
            d.deserialize_any(self)
        }
    }
    impl<'de> Visitor<'de> for Unique {
        type Value = Value;
        fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
            f.write_str("a JSON value")
        }
        fn visit_bool<E: Error>(self, v: bool) -> Result<Value, E> {
            Ok(Value::Bool(v))
        }
        fn visit_i64<E: Error>(self, v: i64) -> Result<Value, E> {
            Ok(Value::from(v))
        }
        fn visit_u64<E: Error>(self, v: u64) -> Result<Value, E> {
            Ok(Value::from(v))
        }
        fn visit_f64<E: Error>(self, v: f64) -> Result<Value, E> {
            Ok(Value::from(v))
        }
        fn visit_str<E: Error>(self, v: &str) -> Result<Value, E> {
            Ok(Value::String(v.to_string()))
        }
        fn visit_string<E: Error>(self, v: String) -> Result<Value, E> {
            Ok(Value::String(v))
        }
        fn visit_unit<E: Error>(self) -> Result<Value, E> {
            Ok(Value::Null)
        }
        fn visit_none<E: Error>(self) -> Result<Value, E> {
            Ok(Value::Null)
        }
        fn visit_seq<A: SeqAccess<'de>>(self, mut seq: A) -> Result<Value, A::Error> {
            let mut out = Vec::new();
            while let Some(v) = seq.next_element_seed(Unique)? {
                out.push(v);
            }
            Ok(Value::Array(out))
        }
        fn visit_map<A: MapAccess<'de>>(self, mut map: A) -> Result<Value, A::Error> {
            let mut out = serde_json::Map::new();
            while let Some(k) = map.next_key::<String>()? {
                if out.contains_key(&k) {
                    return Err(A::Error::custom(format!(
                        "the key \"{}\" twice in one object",
                        super::name::shown_counted(&k)
                    )));
                }
                let v = map.next_value_seed(Unique)?;
                out.insert(k, v);
            }
            Ok(Value::Object(out))
        }
    }
    let mut d = serde_json::Deserializer::from_str(text);
    let v = Unique.deserialize(&mut d)?;
    d.end()?;
    Ok(v)
}
