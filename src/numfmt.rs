//! Numbers read from input files, as error and warning lines print them: Rust's shortest
//! round-trip form between 10⁻⁴ and 10⁹ (`11.828`, `0.25`), its exponent form outside
//! (`1e300`, `-2.5e-7`), so a 10³⁰⁰ in a file is `1e300` in the message, not 301 digits.
//! Either form parses back to the same `f64`: the number in the message can be searched for
//! in the file.
use std::fmt;

/// An `f64` or `f32` printed for a message (module docs): `format!("scale {}", Num(s))`. An
/// `f32` keeps its own shortest form (`0.1`, not `0.10000000149011612`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Num<T = f64>(pub T);

impl<T: Into<f64> + Copy + fmt::Display + fmt::LowerExp> fmt::Display for Num<T> {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        let x: f64 = self.0.into();
        let a = x.abs();
        if !x.is_finite() || a == 0.0 || (1e-4..1e9).contains(&a) {
            write!(f, "{}", self.0)
        } else {
            write!(f, "{:e}", self.0)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::Num;

    #[test]
    fn numbers_print_short_and_parse_back() {
        // By hand.
        for (x, s) in [
            (1e300, "1e300"),
            (-1e300, "-1e300"),
            (1e30, "1e30"),
            (-2.5e-7, "-2.5e-7"),
            (11.828, "11.828"),
            (0.25, "0.25"),
            (123_456_789.0, "123456789"),
            (1e9, "1e9"),
            (1.5e9, "1.5e9"),
            (0.0001, "0.0001"),
            (0.00005, "5e-5"),
            (0.0, "0"),
            (-0.0, "-0"),
            (f64::NAN, "NaN"),
            (f64::INFINITY, "inf"),
            (f64::MIN_POSITIVE, "2.2250738585072014e-308"),
        ] {
            assert_eq!(Num(x).to_string(), s, "{x:?}");
        }
        // An f32 in its own shortest form.
        for (x, s) in [(0.1f32, "0.1"), (1e30f32, "1e30"), (-3.5e-6f32, "-3.5e-6")] {
            assert_eq!(Num(x).to_string(), s, "{x:?}");
        }
        // Any finite value: at most 24 characters, and it parses back to itself.
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        for _ in 0..100_000 {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            let x = f64::from_bits(state);
            if !x.is_finite() {
                continue;
            }
            let s = Num(x).to_string();
            assert!(s.len() <= 24, "{s}");
            assert_eq!(s.parse::<f64>().unwrap().to_bits(), x.to_bits(), "{s}");
        }
    }
}
