//! `sin` for the probe's sinusoid `s_i = sin(w_i * tau)`, without a libm call per lane.
//!
//! libm's `sin` costs ~20-30 ns on the target machine, which alone would spend the whole 100 ns budget of
//! a D = 6 probe/report pair. Here the argument is reduced by Cody-Waite with fdlibm's
//! three-part pi/2 and evaluated with fdlibm's `__kernel_sin`/`__kernel_cos` polynomials: inlinable and
//! branch-free, so a loop over the lanes vectorizes, and within 2.2e-16 (one ulp of 1.0) of libm's `sin` (tested below), far inside
//! the 1e-9 to which clients must reproduce the law. Arguments beyond [`REDUCTION_LIMIT`] need libm.

use std::f64::consts::FRAC_2_PI;

/// Largest |x| reduced here: `k * PIO2_1` stays exact for quadrant numbers `k < 2^20`.
pub const REDUCTION_LIMIT: f64 = 1000000.0;

/// 1.5 * 2^52: adding it rounds to an integer held in the low mantissa bits.
const SHIFTER: f64 = 6_755_399_441_055_744.0;
/// pi/2 split into 33-bit parts (fdlibm `pio2_1`, `pio2_2`, `pio2_3`).
const PIO2_1: f64 = 1.5707963267341256;
const PIO2_2: f64 = 6.077100506303966e-11;
const PIO2_3: f64 = 2.0222662487111665e-21;

/// fdlibm `k_sin.c` minimax coefficients for sin on [-pi/4, pi/4].
const S1: f64 = -0.16666666666666632;
const S2: f64 = 0.00833333333332249;
const S3: f64 = -0.0001984126982985795;
const S4: f64 = 2.7557313707070068e-06;
const S5: f64 = -2.5050760253406863e-08;
const S6: f64 = 1.58969099521155e-10;

/// fdlibm `k_cos.c` minimax coefficients for cos on [-pi/4, pi/4].
const C1: f64 = 0.0416666666666666;
const C2: f64 = -0.001388888888887411;
const C3: f64 = 2.480158728947673e-05;
const C4: f64 = -2.7557314351390663e-07;
const C5: f64 = 2.087572321298175e-09;
const C6: f64 = -1.1359647557788195e-11;

#[inline(always)]
pub fn sin_reduced(x: f64) -> f64 {
    let shifted = x * FRAC_2_PI + SHIFTER;
    let quadrant = shifted.to_bits();
    let k = shifted - SHIFTER;
    // k * PIO2_1 is exact and close to x, so the first subtraction is exact; the two small parts are
    // summed apart from it to shorten the dependency chain.
    let r = (x - k * PIO2_1) - (k * PIO2_2 + k * PIO2_3);
    // Estrin's scheme instead of Horner's: a single lane (D = 1) is bound by latency, not throughput.
    let z = r * r;
    let z2 = z * z;
    let z4 = z2 * z2;
    let sin_poly = (S1 + z * S2) + z2 * (S3 + z * S4) + z4 * (S5 + z * S6);
    let sin_r = r + z * r * sin_poly;
    let cos_poly = (C1 + z * C2) + z2 * (C3 + z * C4) + z4 * (C5 + z * C6);
    let half_z = 0.5 * z;
    let w = 1.0 - half_z;
    let cos_r = w + (((1.0 - w) - half_z) + z2 * cos_poly);
    // Quadrant selection by bit masks, not branches: the quadrant of each lane changes from step to
    // step with no pattern a branch predictor could learn, and masks keep the lane loop vectorizable.
    let use_cos = 0u64.wrapping_sub(quadrant & 1);
    let magnitude = (sin_r.to_bits() & !use_cos) | (cos_r.to_bits() & use_cos);
    let sign = (quadrant & 2) << 62;
    f64::from_bits(magnitude ^ sign)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Largest |ours - libm| over `xs`.
    fn max_error(xs: impl Iterator<Item = f64>) -> f64 {
        xs.map(|x| (sin_reduced(x) - x.sin()).abs())
            .fold(0.0, f64::max)
    }

    /// One ulp of 1.0.
    const TOLERANCE: f64 = f64::EPSILON;

    #[test]
    fn matches_libm_on_the_probe_grid() {
        // w * (t * dt) as the session computes it: long episodes, frequencies up to Nyquist.
        let cases: [(f64, f64); 4] = [(0.01, 60.0), (0.01, 75.0), (0.002, 1570.0), (0.05, 62.8)];
        let grid = cases
            .into_iter()
            .flat_map(|(dt, w)| (0..200_000u64).map(move |t| w * (t as f64 * dt)));
        assert!(max_error(grid) <= TOLERANCE);
    }

    #[test]
    fn matches_libm_across_the_reduction_range() {
        // A fixed-seed LCG covers magnitudes from 1e-9 to the limit, both signs.
        let mut state = 0x2545_f491_4f6c_dd1d_u64;
        let xs = std::iter::from_fn(move || {
            state = state
                .wrapping_mul(6_364_136_223_846_793_005)
                .wrapping_add(1_442_695_040_888_963_407);
            let unit = (state >> 11) as f64 / (1u64 << 53) as f64;
            let magnitude = 10f64.powf(-9.0 + 15.0 * unit).min(REDUCTION_LIMIT);
            Some(if state & 1 == 0 {
                magnitude
            } else {
                -magnitude
            })
        });
        assert!(max_error(xs.take(1_000_000)) <= TOLERANCE);
    }

    #[test]
    fn exact_at_zero_and_close_near_quadrant_edges() {
        assert_eq!(sin_reduced(0.0).to_bits(), 0.0f64.to_bits());
        let edges = (1..2000).flat_map(|k| {
            let x = k as f64 * std::f64::consts::FRAC_PI_4;
            [x.next_down(), x, x.next_up()]
        });
        assert!(max_error(edges) <= TOLERANCE);
        assert!(max_error([REDUCTION_LIMIT, -REDUCTION_LIMIT].into_iter()) <= TOLERANCE);
    }
}
