//! Elementary functions in `f32` without library calls, branch-free so that loops over slices
//! vectorise: `e^x` for `x ≤ 0` (the rasterizer's α, SAM's decoder's softmaxes) and `erf`/GELU
//! (SAM's decoder).

/// `e^x` for `x ≤ 0` in `f32` without a library call, so that a row of pixels vectorises:
/// Cody–Waite reduction `x = n·ln 2 + r` and Cephes' degree-6 polynomial for `e^r` (within
/// 2 ulp of the correctly rounded value for `x ∈ [−87, 0]`; below, 0 is returned).
#[inline(always)]
pub fn exp_neg(x: f32) -> f32 {
    let xc = x.clamp(-87.0, 0.0);
    let n = (xc * std::f32::consts::LOG2_E + 0.5).floor();
    let r = xc - n * 0.693_359_4 + n * 2.121_944_4e-4;
    let p = ((((1.987_569_1e-4 * r + 1.398_199_9e-3) * r + 8.333_452e-3) * r + 4.166_579_6e-2) * r
        + 1.666_666_5e-1)
        * r
        + 0.5;
    let e = p * r * r + r + 1.0;
    // n ∈ [−126, 0]: 2^n is a normal f32 built from its exponent bits. The biased exponent
    // n + 127 ∈ [1, 127] is read from the mantissa of (n + 127) + 2²³ (exact for an integer
    // below 2²³), which vectorises where the saturating `as i32` does not.
    let biased = ((n + 127.0) + 8_388_608.0).to_bits() - 0x4B00_0000;
    let scale = f32::from_bits(biased << 23);
    if x < -87.0 { 0.0 } else { e * scale }
}

/// `x.round().clamp(0.0, 255.0) as u8` (rounding half away from zero; NaN gives 0) without
/// the library's `roundf` call: the truncation `t` of a non-negative `x` and its exact
/// fraction `x − t` (exact below 2²⁴; from 2²⁴ to 2³² `x` is an integer and the fraction 0;
/// above, `t` saturates and the result is 255 either way) decide the rounding. Negative values
/// and NaN truncate to 0, as they round and clamp to 0.
#[inline(always)]
pub fn round_u8(x: f32) -> u8 {
    let t = x as u32;
    let up = u32::from(x - t as f32 >= 0.5);
    t.saturating_add(up).min(255) as u8
}

/// `erf(x)` by Abramowitz & Stegun 7.1.26 (`1 − t·P(t)·e^{−x²}`, `t = 1/(1 + 0.3275911·|x|)`),
/// absolute error ≤ 1.5·10⁻⁷ in exact arithmetic, ≤ 6·10⁻⁷ evaluated in `f32`; NaN stays NaN.
#[inline(always)]
pub fn erf(x: f32) -> f32 {
    let a = x.abs();
    let t = 1.0 / (1.0 + 0.327_591_1 * a);
    let p = t
        * (0.254_829_6
            + t * (-0.284_496_74 + t * (1.421_413_7 + t * (-1.453_152 + t * 1.061_405_4))));
    (1.0 - p * exp_neg(-a * a)).copysign(x)
}

/// The exact (erf) GELU, `½·x·(1 + erf(x/√2))`, as `torch.nn.GELU()` and ONNX `Gelu`.
#[inline(always)]
pub fn gelu(x: f32) -> f32 {
    0.5 * x * (1.0 + erf(x * std::f32::consts::FRAC_1_SQRT_2))
}

/// Runs `f` under the widest instruction set the CPU has (`pulp`'s runtime dispatch), so that
/// the loops it inlines vectorise (AVX2 + FMA where present).
#[inline(always)]
pub fn simd<R>(f: impl FnOnce() -> R) -> R {
    pulp::Arch::new().dispatch(f)
}

/// [`gelu`] of every value, under the widest instruction set the CPU has (`pulp`'s dispatch).
pub fn gelu_in_place(v: &mut [f32]) {
    struct Op<'a>(&'a mut [f32]);
    impl pulp::WithSimd for Op<'_> {
        type Output = ();
        #[inline(always)]
        fn with_simd<S: pulp::Simd>(self, _simd: S) {
            for x in self.0.iter_mut() {
                *x = gelu(*x);
            }
        }
    }
    pulp::Arch::new().dispatch(Op(v));
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn round_u8_is_the_library_round_and_clamp() {
        let want = |x: f32| x.round().clamp(0.0, 255.0) as u8;
        // Every float of [0.25, 300] (all the halves and their neighbours among them), and a
        // stride through every bit pattern (negatives, NaNs, infinities, huge and tiny values).
        let mut x = 0.25f32;
        while x <= 300.0 {
            assert_eq!(round_u8(x), want(x), "{x:e} ({:#x})", x.to_bits());
            x = x.next_up();
        }
        for bits in (0..=u32::MAX).step_by(4099) {
            let x = f32::from_bits(bits);
            assert_eq!(round_u8(x), want(x), "{x:e} ({bits:#x})");
        }
        for x in [
            0.499_999_97f32,
            0.5,
            254.5,
            255.5,
            16_777_215.0,
            4.3e9,
            -0.0,
        ] {
            assert_eq!(round_u8(x), want(x), "{x:e}");
        }
    }

    #[test]
    fn exp_neg_is_within_2_ulp_of_the_f64_exponential() {
        let mut x = -87.0f32;
        while x <= 0.0 {
            let want = f64::from(x).exp();
            let got = f64::from(exp_neg(x));
            let ulp = f64::from(f32::from_bits((want as f32).to_bits() + 1) - want as f32);
            assert!((got - want).abs() <= 2.0 * ulp, "e^{x}: {got} vs {want}");
            x += 0.000_37;
        }
        assert_eq!(exp_neg(0.0), 1.0);
        assert_eq!(exp_neg(-100.0), 0.0);
    }

    /// erf in f64 from its Maclaurin series (|x| ≤ 3, 80 terms) and the continued fraction of
    /// erfc (|x| > 3): independent of the approximation under test.
    fn erf_ref(x: f64) -> f64 {
        let a = x.abs();
        let v = if a <= 3.0 {
            let (mut term, mut sum) = (a, a);
            for n in 1..200 {
                term *= -a * a / n as f64;
                sum += term / (2 * n + 1) as f64;
            }
            sum * 2.0 / std::f64::consts::PI.sqrt()
        } else {
            // erfc(a) = e^{−a²}/√π · 1/(a + (1/2)/(a + 1/(a + (3/2)/(a + 2/(a + …)))))
            let mut f = a;
            for k in (1..60).rev() {
                f = a + (k as f64 / 2.0) / f;
            }
            1.0 - (-a * a).exp() / std::f64::consts::PI.sqrt() / f
        };
        v.copysign(x)
    }

    #[test]
    fn erf_and_gelu_are_within_their_stated_error() {
        let mut x = -9.0f32;
        let mut worst = 0f64;
        while x <= 9.0 {
            let e = (f64::from(erf(x)) - erf_ref(f64::from(x))).abs();
            worst = worst.max(e);
            let g = f64::from(x) * 0.5 * (1.0 + erf_ref(f64::from(x) / 2f64.sqrt()));
            // erf's error times ½|x|, plus the f32 rounding of the result
            assert!(
                (f64::from(gelu(x)) - g).abs()
                    <= 3e-7 * f64::from(x).abs() + 2.5e-7 * g.abs().max(1.0),
                "gelu({x}): {} vs {g}",
                gelu(x)
            );
            x += 0.001_3;
        }
        assert!(worst <= 6.0e-7, "erf error {worst}");
        assert!(erf(f32::NAN).is_nan());
        assert!(erf(0.0).abs() <= 6.0e-7);
        let mut v: Vec<f32> = (-50..50).map(|i| i as f32 * 0.1).collect();
        let want: Vec<f32> = v.iter().map(|&x| gelu(x)).collect();
        gelu_in_place(&mut v);
        assert_eq!(v, want);
    }
}
