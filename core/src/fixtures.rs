//! Test fixtures shared by the core's unit tests: the XY stage's x stack (host-sim's seed 002
//! set, y = d·(u − h) with h in volts, n = 1) over its 0–120 V window.

use crate::bouc_wen::{BoucWen, BoucWenParams};

/// The x stack's Bouc-Wen set over 0–120 V with exponent `n` (β and γ scaled by H^(1 − n), so
/// that the saturation level H = A/(β + γ)^(1/n) stays where it is and the loop keeps its shape;
/// exactly the stack's set for n = 1) and state limit `state_limit`.
pub fn x_stack(n: f32, state_limit: f32) -> BoucWen {
    let level = 0.18522f32 / (0.029586 - 0.020710);
    let scale = libm::powf(level, 1.0 - n);
    BoucWen::with_input_range(
        BoucWenParams {
            a: 0.18522,
            beta: 0.029586 * scale,
            gamma: -0.020710 * scale,
            n,
        },
        0.0,
        120.0,
        state_limit,
    )
    .unwrap()
}
