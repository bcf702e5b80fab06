//! SplitMix64 (Steele, Lea & Flood 2014; the finaliser of `java.util.SplittableRandom`): the one
//! deterministic, well-mixed hash of an integer used for seeded sampling (associate's link
//! sample, refine's voxel sample, the simulator's per-object streams). A library module.

/// The SplitMix64 output for state `x`: `x + γ` (γ = 2⁶⁴/φ) through the two xor-shift-multiply
/// rounds.
pub fn splitmix64(x: u64) -> u64 {
    let mut z = x.wrapping_add(GAMMA);
    z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
    z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
    z ^ (z >> 31)
}

/// The golden-ratio increment of SplitMix64.
pub const GAMMA: u64 = 0x9E37_79B9_7F4A_7C15;

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn first_outputs_of_the_reference_generator() {
        // The reference generator with seed 0 returns splitmix64(k·γ) for k = 0, 1, …; its
        // first output is the published value 0xE220A8397B1DCDAF.
        assert_eq!(splitmix64(0), 0xE220_A839_7B1D_CDAF);
        assert_eq!(splitmix64(GAMMA), 0x6E78_9E6A_A1B9_65F4);
    }
}
