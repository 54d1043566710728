//! JSON Schema's reading of request bodies, so that the server accepts exactly what
//! `openapi.yaml` describes: an optional field may be absent but is never `null` (serde would
//! read `null` as absent), and an `integer` may be written with a zero fraction (`6.0` is an
//! integer to JSON Schema, while serde refuses it for `usize`).

use std::fmt;

use serde::de::{self, Deserialize, Deserializer, Visitor};
use serde_json::{Map, Number, Value};

use super::ApiError;

/// For `#[serde(default, deserialize_with = "present")]` on an `Option<T>` field: absent is
/// `None`, `null` is an error ("invalid type: null, expected ..."), anything else is `T`.
pub fn present<'de, D: Deserializer<'de>, T: Deserialize<'de>>(d: D) -> Result<Option<T>, D::Error> {
    T::deserialize(d).map(Some)
}

/// A non-negative integer (an index, a count) written as `6` or `6.0`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Index(pub usize);

impl<'de> Deserialize<'de> for Index {
    fn deserialize<D: Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct IndexVisitor;
        impl Visitor<'_> for IndexVisitor {
            type Value = Index;

            fn expecting(&self, f: &mut fmt::Formatter) -> fmt::Result {
                f.write_str("a non-negative integer")
            }

            fn visit_u64<E: de::Error>(self, v: u64) -> Result<Index, E> {
                usize::try_from(v).map(Index).map_err(|_| E::custom(format!("{v} is too large")))
            }

            fn visit_i64<E: de::Error>(self, v: i64) -> Result<Index, E> {
                u64::try_from(v)
                    .map_err(|_| E::invalid_value(de::Unexpected::Signed(v), &self))
                    .and_then(|v| self.visit_u64(v))
            }

            fn visit_f64<E: de::Error>(self, v: f64) -> Result<Index, E> {
                match integral_u64(v) {
                    Some(n) => self.visit_u64(n),
                    None => Err(E::invalid_value(de::Unexpected::Float(v), &self)),
                }
            }
        }
        d.deserialize_any(IndexVisitor)
    }
}

/// `v` as a u64 when it is a whole number in u64's range.
fn integral_u64(v: f64) -> Option<u64> {
    // 2^64 is exactly representable; every whole f64 below it fits a u64 (NaN is in no range).
    ((0.0..18_446_744_073_709_551_616.0).contains(&v) && v.fract() == 0.0).then_some(v as u64)
}

/// Checks the `params` object of a job before it is read into `FitParams`: a parameter that is
/// `null` is a 422 naming it (leave it out for its default), and whole numbers written as
/// floats (`6.0`) become integers, so that integer parameters accept them as JSON Schema does
/// (float parameters read an integer just as well).
pub fn fit_params_object(value: Value) -> Result<Map<String, Value>, ApiError> {
    let Value::Object(mut params) = value else {
        return Err(ApiError::invalid("params", "params must be an object of hyper-parameters"));
    };
    for (name, v) in params.iter_mut() {
        match v {
            Value::Null => {
                return Err(ApiError::invalid(
                    format!("params.{name}"),
                    format!("params.{name} is null; leave a parameter out to get its default"),
                ));
            }
            Value::Number(n) if !(n.is_u64() || n.is_i64()) => {
                if let Some(whole) = n.as_f64().and_then(integral_u64) {
                    *n = Number::from(whole);
                }
            }
            _ => {}
        }
    }
    Ok(params)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[derive(Debug, serde::Deserialize)]
    #[allow(dead_code)]
    struct Body {
        #[serde(default, deserialize_with = "present")]
        t: Option<f64>,
        #[serde(default, deserialize_with = "present")]
        frame: Option<Index>,
        #[serde(default, deserialize_with = "present")]
        indices: Option<Vec<Index>>,
    }

    #[test]
    fn absent_is_none_and_null_is_refused() {
        let b: Body = serde_json::from_str("{}").unwrap();
        assert!(b.t.is_none() && b.frame.is_none() && b.indices.is_none());
        for body in [r#"{"t": null}"#, r#"{"frame": null}"#, r#"{"indices": null}"#, r#"{"indices": [null]}"#] {
            let e = serde_json::from_str::<Body>(body).unwrap_err();
            assert!(e.to_string().contains("null"), "{body}: {e}");
        }
    }

    #[test]
    fn indices_are_whole_numbers_with_or_without_a_fraction() {
        let b: Body = serde_json::from_str(r#"{"frame": 2.0, "indices": [0, 5.0, 18446744073709551615]}"#).unwrap();
        assert_eq!(b.frame, Some(Index(2)));
        assert_eq!(b.indices.unwrap(), vec![Index(0), Index(5), Index(usize::MAX)]);
        for body in
            [r#"{"frame": 2.5}"#, r#"{"frame": -1}"#, r#"{"frame": -1.0}"#, r#"{"frame": 1e20}"#, r#"{"frame": "1"}"#]
        {
            assert!(serde_json::from_str::<Body>(body).is_err(), "{body}");
        }
    }

    #[test]
    fn params_refuse_null_and_read_whole_floats_as_integers() {
        let p = fit_params_object(serde_json::json!({ "hidden_width": 6.0, "learning_rate": 0.5, "seed": 3 })).unwrap();
        assert_eq!(p["hidden_width"], serde_json::json!(6));
        assert!(p["hidden_width"].is_u64());
        assert_eq!(p["learning_rate"], serde_json::json!(0.5));
        let e = fit_params_object(serde_json::json!({ "moving_bodies": null })).unwrap_err();
        assert!(matches!(e, ApiError::Invalid { parameter: Some(p), .. } if p == "params.moving_bodies"));
        assert!(fit_params_object(serde_json::json!([1])).is_err());
    }
}
