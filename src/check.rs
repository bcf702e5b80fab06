//! The range checks of every options `validate` (one wording for all): a value must be a
//! number inside an interval whose ends are open, closed or absent. NaN is never inside. A
//! library module: it imports only `numfmt` (a value of 10³⁰⁰ is printed `1e300`).

use crate::numfmt::Num;

/// One end of an interval.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum End {
    /// The end value belongs to the interval.
    Closed(f64),
    /// The end value does not.
    Open(f64),
    /// No bound on this side (infinity allowed).
    Unbounded,
}

/// Checks `lo ≤/< value ≤/< hi` (`f32` or `f64`); the error reads
/// `"{name} must lie in [lo, hi), got {value}"`.
pub fn range<T: Into<f64> + Copy + std::fmt::Display + std::fmt::LowerExp>(
    name: &str,
    value: T,
    lo: End,
    hi: End,
) -> Result<(), String> {
    let v: f64 = value.into();
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
    let l = match lo {
        End::Closed(a) => format!("[{a}"),
        End::Open(a) => format!("({a}"),
        End::Unbounded => "(-∞".to_string(),
    };
    let h = match hi {
        End::Closed(b) => format!("{b}]"),
        End::Open(b) => format!("{b})"),
        End::Unbounded => "∞)".to_string(),
    };
    Err(format!("{name} must lie in {l}, {h}, got {}", Num(value)))
}

/// `v ∈ [0, 1]`.
pub fn unit<T: Into<f64> + Copy + std::fmt::Display + std::fmt::LowerExp>(
    name: &str,
    v: T,
) -> Result<(), String> {
    range(name, v, End::Closed(0.0), End::Closed(1.0))
}

/// `v` finite and `≥ 0`.
pub fn non_negative<T: Into<f64> + Copy + std::fmt::Display + std::fmt::LowerExp>(
    name: &str,
    v: T,
) -> Result<(), String> {
    let x: f64 = v.into();
    if x.is_finite() && x >= 0.0 {
        Ok(())
    } else {
        Err(format!("{name} must be finite and ≥ 0, got {}", Num(v)))
    }
}

/// `v` finite and `> 0`.
pub fn positive<T: Into<f64> + Copy + std::fmt::Display + std::fmt::LowerExp>(
    name: &str,
    v: T,
) -> Result<(), String> {
    let x: f64 = v.into();
    if x.is_finite() && x > 0.0 {
        Ok(())
    } else {
        Err(format!("{name} must be finite and > 0, got {}", Num(v)))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn ends_and_nan() {
        assert!(range("a", 0.0, End::Closed(0.0), End::Open(1.0)).is_ok());
        assert!(range("a", 1.0, End::Closed(0.0), End::Open(1.0)).is_err());
        assert!(range("a", 0.0, End::Open(0.0), End::Unbounded).is_err());
        assert!(range("a", f64::INFINITY, End::Open(0.0), End::Unbounded).is_ok());
        assert!(range("a", f64::NAN, End::Unbounded, End::Unbounded).is_err());
        assert_eq!(
            range("tau", 2.0, End::Closed(-1.0), End::Open(1.0)).unwrap_err(),
            "tau must lie in [-1, 1), got 2"
        );
        assert_eq!(
            unit("tau_q", 1e300).unwrap_err(),
            "tau_q must lie in [0, 1], got 1e300"
        );
        assert_eq!(
            positive("size", -1e30f32).unwrap_err(),
            "size must be finite and > 0, got -1e30"
        );
        assert!(unit("u", f64::NAN).is_err() && unit("u", 1.0).is_ok());
        assert!(non_negative("n", 0.0).is_ok() && non_negative("n", f64::INFINITY).is_err());
        assert!(positive("p", 0.0).is_err() && positive("p", 1e-300).is_ok());
    }
}
