//! The range checks of every options `validate` (one wording for all): a value must be a
//! number inside an interval whose ends are open, closed or absent. NaN is never inside. A
//! failed check is one typed error, [`OutOfRange`], which every stage's error type wraps (a
//! value of 10³⁰⁰ is printed `1e300`, [`crate::numfmt::Num`]). A library module: it imports
//! only `numfmt`.

use std::fmt;

use crate::numfmt::Num;

/// One end of an interval.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum End {
    /// The end value belongs to the interval.
    Closed(f64),
    /// The end value does not (`Open(f64::INFINITY)` as the upper end: any finite value).
    Open(f64),
    /// No bound on this side (infinity allowed).
    Unbounded,
}

/// A checked value as the message prints it: an `f32` keeps its own shortest form (`0.1`,
/// not `0.10000000149011612`); counts are exact.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Value {
    F64(f64),
    F32(f32),
    Count(u64),
}

impl Value {
    fn get(self) -> f64 {
        match self {
            Value::F64(v) => v,
            Value::F32(v) => f64::from(v),
            Value::Count(v) => v as f64,
        }
    }
}

impl From<f64> for Value {
    fn from(v: f64) -> Value {
        Value::F64(v)
    }
}

impl From<f32> for Value {
    fn from(v: f32) -> Value {
        Value::F32(v)
    }
}

impl From<usize> for Value {
    fn from(v: usize) -> Value {
        Value::Count(v as u64)
    }
}

impl From<u32> for Value {
    fn from(v: u32) -> Value {
        Value::Count(u64::from(v))
    }
}

impl From<u64> for Value {
    fn from(v: u64) -> Value {
        Value::Count(v)
    }
}

impl fmt::Display for Value {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Value::F64(v) => write!(f, "{}", Num(*v)),
            Value::F32(v) => write!(f, "{}", Num(*v)),
            Value::Count(v) => write!(f, "{v}"),
        }
    }
}

/// An option outside its interval: `name` (as the options struct and the `--config` file
/// spell it), the value given and the interval's ends. One line:
/// `tau must lie in [-1, 1), got 2`, `size must be finite and > 0, got -1e30`,
/// `min_views must be ≥ 1, got 0`.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub struct OutOfRange {
    pub name: String,
    pub value: Value,
    pub lo: End,
    pub hi: End,
}

/// `a` as an interval end: whole numbers without a fraction (`1`, not `1.0`); an end that is
/// an `f32` widened (an `f32` constant as the bound) in the `f32`'s own shortest form
/// (`0.003921569`, not `0.003921568859368563`).
fn end_value(a: f64) -> String {
    let narrow = a as f32;
    if a.fract() != 0.0 && f64::from(narrow) == a {
        format!("{}", Num(narrow))
    } else {
        format!("{}", Num(a))
    }
}

impl fmt::Display for OutOfRange {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let name = &self.name;
        let finite_only = self.hi == End::Open(f64::INFINITY);
        match (self.lo, self.hi) {
            (End::Closed(a), End::Unbounded) => write!(f, "{name} must be ≥ {}", end_value(a))?,
            (End::Open(a), End::Unbounded) => write!(f, "{name} must be > {}", end_value(a))?,
            (End::Closed(a), _) if finite_only => {
                write!(f, "{name} must be finite and ≥ {}", end_value(a))?
            }
            (End::Open(a), _) if finite_only => {
                write!(f, "{name} must be finite and > {}", end_value(a))?
            }
            (lo, hi) => {
                let l = match lo {
                    End::Closed(a) => format!("[{}", end_value(a)),
                    End::Open(a) => format!("({}", end_value(a)),
                    End::Unbounded => "(-∞".to_string(),
                };
                let h = match hi {
                    End::Closed(b) => format!("{}]", end_value(b)),
                    End::Open(b) => format!("{})", end_value(b)),
                    End::Unbounded => "∞)".to_string(),
                };
                write!(f, "{name} must lie in {l}, {h}")?
            }
        }
        write!(f, ", got {}", self.value)
    }
}

/// Checks `lo ≤/< value ≤/< hi` (`f32`, `f64` or a count); the error reads
/// `"{name} must lie in [lo, hi), got {value}"`.
pub fn range(name: &str, value: impl Into<Value>, lo: End, hi: End) -> Result<(), OutOfRange> {
    let value = value.into();
    let v = value.get();
    let above = match lo {
        End::Closed(a) => v >= a,
        End::Open(a) => v > a,
        End::Unbounded => !v.is_nan(),
    };
    let below = match hi {
        End::Closed(b) => v <= b,
        End::Open(b) => v < b,
        End::Unbounded => !v.is_nan(),
    };
    if above && below {
        return Ok(());
    }
    Err(OutOfRange {
        name: name.to_string(),
        value,
        lo,
        hi,
    })
}

/// `v ∈ [0, 1]`.
pub fn unit(name: &str, v: impl Into<Value>) -> Result<(), OutOfRange> {
    range(name, v, End::Closed(0.0), End::Closed(1.0))
}

/// `v` finite and `≥ 0`.
pub fn non_negative(name: &str, v: impl Into<Value>) -> Result<(), OutOfRange> {
    range(name, v, End::Closed(0.0), End::Open(f64::INFINITY))
}

/// `v` finite and `> 0`.
pub fn positive(name: &str, v: impl Into<Value>) -> Result<(), OutOfRange> {
    range(name, v, End::Open(0.0), End::Open(f64::INFINITY))
}

/// A count of at least `min` (`min_views must be ≥ 1, got 0`).
pub fn at_least(name: &str, v: usize, min: usize) -> Result<(), OutOfRange> {
    range(name, v, End::Closed(min as f64), End::Unbounded)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn msg(r: Result<(), OutOfRange>) -> String {
        r.unwrap_err().to_string()
    }

    #[test]
    fn ends_and_nan() {
        assert!(range("a", 0.0, End::Closed(0.0), End::Open(1.0)).is_ok());
        assert!(range("a", 1.0, End::Closed(0.0), End::Open(1.0)).is_err());
        assert!(range("a", 0.0, End::Open(0.0), End::Unbounded).is_err());
        assert!(range("a", f64::INFINITY, End::Open(0.0), End::Unbounded).is_ok());
        assert!(range("a", f64::NAN, End::Unbounded, End::Unbounded).is_err());
        assert_eq!(
            msg(range("tau", 2.0, End::Closed(-1.0), End::Open(1.0))),
            "tau must lie in [-1, 1), got 2"
        );
        assert_eq!(
            msg(unit("tau_q", 1e300)),
            "tau_q must lie in [0, 1], got 1e300"
        );
        assert_eq!(
            msg(positive("size", -1e30f32)),
            "size must be finite and > 0, got -1e30"
        );
        assert_eq!(
            msg(non_negative("gamma", f32::NAN)),
            "gamma must be finite and ≥ 0, got NaN"
        );
        assert_eq!(
            msg(at_least("min_views", 0, 1)),
            "min_views must be ≥ 1, got 0"
        );
        assert_eq!(
            msg(range(
                "top_k",
                5000usize,
                End::Closed(0.0),
                End::Closed(4096.0)
            )),
            "top_k must lie in [0, 4096], got 5000"
        );
        // An f32 keeps its own shortest form.
        assert_eq!(
            msg(range("t_stop", 1.1f32, End::Closed(0.0), End::Open(1.0))),
            "t_stop must lie in [0, 1), got 1.1"
        );
        // … and so does an end that is an f32 widened (1/255 as f32).
        let inria = f64::from(1.0f32 / 255.0);
        assert_eq!(
            msg(range(
                "alpha_min",
                0.001f32,
                End::Closed(inria),
                End::Open(0.99)
            )),
            "alpha_min must lie in [0.003921569, 0.99), got 0.001"
        );
        assert!(unit("u", f64::NAN).is_err() && unit("u", 1.0).is_ok());
        assert!(non_negative("n", 0.0).is_ok() && non_negative("n", f64::INFINITY).is_err());
        assert!(positive("p", 0.0).is_err() && positive("p", 1e-300).is_ok());
        // The typed parts.
        let e = range("gamma", -2.0f32, End::Closed(-1.0), End::Closed(1.0)).unwrap_err();
        assert_eq!(
            (e.name.as_str(), e.value, e.lo, e.hi),
            (
                "gamma",
                Value::F32(-2.0),
                End::Closed(-1.0),
                End::Closed(1.0)
            )
        );
    }
}
