//! The inverse of the effect chain (`piezo_core::effects`) around the compensator, per tick, for
//! both axes: what [`crate::xy_loop::TwoAxisLoop`] runs when the parameter file has effects.
//!
//! # The forward chain it inverts (per axis, command sample j, loop period T)
//! ```text
//! w[j] = H(u[j])                                   hysteresis model (the compensator's)  \[m\]
//! s[j] = w[j] + e·(u[j−1] − u_c)² + Σᵢ gᵢ·xᵢ[j]    even term and creep (known before u[j])
//! z[j] = M(s)[j]                                   second-order mode (unit DC gain)
//! y[k] = z(k − D) + r_d·k·T + κ·z_other(k − D)     delay D [samples], drift r_d [m/s], coupling κ
//! ```
//!
//! # One tick ([`InverseChain::next_targets`], then [`InverseChain::commit`])
//! The reference generator is a function of the tick index, so it is simply sampled
//! `L = M + max_axes ⌈D⌉` ticks ahead (M = 1 if either axis has a mode, for the mode inverse's
//! central difference; L ≤ 65) into a ring of [`REFERENCE_RING`] samples: at reference tick j the
//! ring holds r\[0..=j + L\] (the last [`REFERENCE_RING`] of them). With q = j + M, per axis
//! (c = the command index, the number of commands committed so far):
//!
//! 1. delay and drift: `d[q] = y*(q + D) − r_d·(c + M + D)·T` (linear interpolation between the
//!    ring samples q + ⌊D⌋ and q + ⌊D⌋ + 1: `Effects::interpolate_reference`,
//!    `Effects::drift_for_command_m`);
//! 2. coupling: `(z*_x[q], z*_y[q]) = decouple(κ_x, κ_y, d_x[q], d_y[q])` — exact also for
//!    different delays, since each axis's output at q + D is `z[q] + κ·z_other[q]`;
//! 3. the last three z\* per axis, `z*[q−2], z*[q−1], z*[q]`, give (z\*\[j−1\], z\*\[j\],
//!    z\*\[j+1\]) to `Effects::inverse_target_w` (mode, creep, even term): the target w\*\[j\] for
//!    the compensator, which the loop then guards as before;
//! 4. after the DAC write, [`InverseChain::commit`] advances each axis's effects state with the
//!    voltage actually applied (the guarded one, or the held one in the safe state or after a
//!    failed DAC write) and the w the compensator's model reached — every tick, so that the creep,
//!    mode, delay line and drift clock follow the stage also while the loop is safe.
//!
//! At the first running tick the ring is filled with r\[0..=L\] and z\* before the first sample
//! is z\*\[0\] (as `piezo_core::effects::compensate_axis`). The reported reference of tick j is
//! r\[j\]: the stage output the command of tick j aims at appears at sample j (after the delay).
//!
//! # Latency
//! Because the generator runs L ticks ahead, anything that changes its output — a
//! `set_program`, and **streamed setpoints** ([`crate::reference::Program::Streamed`]) — takes
//! effect L ticks (L·T: at most 6.5 ms at 10 kHz for a 64-sample delay) later than without
//! effects: a streamed setpoint dequeued at tick k is the reference of tick k + L. The queue must
//! be kept L setpoints fuller to have the same slack. While the loop is safe the generator is
//! paused (as without effects); the drift clock is not, so the first ticks after
//! [`crate::xy_loop::TwoAxisLoop::rearm`] see a step in z\* of r_d times the safe time.
//!
//! Never panics, no allocation: ring indices are masked with a power of two, history indices are
//! constants. A non-finite reference sample gives a NaN target, and the compensator holds its
//! voltage (counted in `held_references`) for the up to three ticks that sample is in the
//! history.

use piezo_core::effects::{decouple, Effects, EffectsState};

use crate::reference::ReferenceGenerator;

/// Reference samples kept: a power of two above the largest lead (1 + 64 samples) + 1.
pub const REFERENCE_RING: usize = 128;
const RING_MASK: u32 = REFERENCE_RING as u32 - 1;

/// The inverse effect chain of both axes: settings, effect states, desired-z history and the
/// reference samples taken ahead.
#[derive(Clone, Debug)]
pub struct InverseChain {
    effects: [Effects; 2],
    state: [EffectsState; 2],
    /// Per axis z\*\[q − 2\], z\*\[q − 1\], z\*\[q\] \[m\], q = j + M.
    desired_z_m: [[f32; 3]; 2],
    /// `ring[s & RING_MASK]` = reference sample s (both axes) \[m\].
    ring: [[f32; 2]; REFERENCE_RING],
    /// Reference samples taken from the generator (wrapping).
    pulled: u32,
    /// Reference index j of the next running tick (wrapping).
    index: u32,
    /// L: how far ahead of tick j the generator is sampled.
    lead: u32,
    /// M: 1 if either axis has a mode (z\*\[j + 1\] is needed), else 0.
    mode_lead: u32,
    primed: bool,
}

impl InverseChain {
    /// The chain for the two axes' effects; `None` when both are the identity (then the loop
    /// runs exactly as without effects).
    pub fn new(effects: [Effects; 2]) -> Option<Self> {
        if effects.iter().all(Effects::is_identity) {
            return None;
        }
        let mode_lead = u32::from(effects.iter().any(Effects::has_mode));
        // ⌈D⌉ per axis: the lead without the mode's extra sample.
        let delay_lead = effects
            .iter()
            .map(|e| e.lead_samples() - usize::from(e.has_mode()))
            .max()
            .unwrap_or(0) as u32;
        Some(Self {
            effects,
            state: [EffectsState::new(); 2],
            desired_z_m: [[0.0; 3]; 2],
            ring: [[0.0; 2]; REFERENCE_RING],
            pulled: 0,
            index: 0,
            lead: mode_lead + delay_lead,
            mode_lead,
            primed: false,
        })
    }

    /// L: ticks the reference generator runs ahead of the reference of the current tick.
    pub fn lead_ticks(&self) -> u32 {
        self.lead
    }

    /// The effects of axis `i` (0 = x, 1 = y).
    pub fn effects(&self) -> &[Effects; 2] {
        &self.effects
    }

    /// The effects states (x, y): the controller's copy of the stage's creep, mode, delay line
    /// and drift clock.
    pub fn states(&self) -> &[EffectsState; 2] {
        &self.state
    }

    #[inline(always)]
    fn push(&mut self, sample: [f32; 2]) {
        self.ring[(self.pulled & RING_MASK) as usize] = sample;
        self.pulled = self.pulled.wrapping_add(1);
    }

    #[inline(always)]
    fn sample(&self, index: u32, axis: usize) -> f32 {
        let s = &self.ring[(index & RING_MASK) as usize];
        if axis == 0 {
            s[0]
        } else {
            s[1]
        }
    }

    /// Step 1 for axis `axis` at reference index `q` (command index `command`): y\*(q + D) minus
    /// the drift at that output time.
    #[inline(always)]
    fn delayed_reference(&self, axis: usize, q: u32, command: u32) -> f32 {
        let e = if axis == 0 {
            &self.effects[0]
        } else {
            &self.effects[1]
        };
        let at = q.wrapping_add(e.reference_index_offset() as u32);
        let after = if e.delay_fraction() > 0.0 {
            at.wrapping_add(1)
        } else {
            at
        };
        e.interpolate_reference(self.sample(at, axis), self.sample(after, axis))
            - e.drift_for_command_m(command as usize)
    }

    /// Steps 1 and 2 for both axes at reference index `q`, `ahead` = q − j command samples after
    /// the current command.
    #[inline(always)]
    fn desired(&self, q: u32, ahead: u32) -> (f32, f32) {
        let command = self.state[0].samples().wrapping_add(ahead);
        let dx = self.delayed_reference(0, q, command);
        let dy = self.delayed_reference(1, q, command);
        let (kx, ky) = (
            self.effects[0].params().coupling,
            self.effects[1].params().coupling,
        );
        let (zx, zy) = decouple(kx, ky, dx, dy);
        // `decouple` holds its results finite; a non-finite reference must reach the compensator
        // as NaN (hold), on its own axis and on the axis that couples it in.
        let (x_ok, y_ok) = (dx.is_finite(), dy.is_finite());
        (
            if x_ok && (y_ok || kx == 0.0) {
                zx
            } else {
                f32::NAN
            },
            if y_ok && (x_ok || ky == 0.0) {
                zy
            } else {
                f32::NAN
            },
        )
    }

    /// One running tick: takes the next reference sample from `reference` (the first time, the
    /// L + 1 first ones), and returns the reference of this tick r\[j\] \[m\] and the targets
    /// w\*\[j\] \[m\] for the compensators (NaN where a reference sample is not finite).
    #[inline]
    pub fn next_targets(&mut self, reference: &mut ReferenceGenerator) -> ([f32; 2], [f32; 2]) {
        let j = self.index;
        let q = j.wrapping_add(self.mode_lead);
        if self.primed {
            self.push(reference.next_setpoint());
            let (zx, zy) = self.desired(q, self.mode_lead);
            for (history, z) in self.desired_z_m.iter_mut().zip([zx, zy]) {
                *history = [history[1], history[2], z];
            }
        } else {
            for _ in 0..=self.lead {
                self.push(reference.next_setpoint());
            }
            // z* before the first sample is z*[0].
            let (x0, y0) = self.desired(j, 0);
            let (x1, y1) = self.desired(q, self.mode_lead);
            self.desired_z_m = if self.mode_lead == 1 {
                [[x0, x0, x1], [y0, y0, y1]]
            } else {
                [[x0, x0, x0], [y0, y0, y0]]
            };
            self.primed = true;
        }
        let now = [self.sample(j, 0), self.sample(j, 1)];
        let mut target = [0.0; 2];
        for ((t, (e, s)), h) in target
            .iter_mut()
            .zip(self.effects.iter().zip(self.state.iter()))
            .zip(self.desired_z_m.iter())
        {
            let (previous, current, next) = if self.mode_lead == 1 {
                (h[0], h[1], h[2])
            } else {
                (h[1], h[2], h[2])
            };
            *t = e.inverse_target_w(s, previous, current, next);
        }
        self.index = j.wrapping_add(1);
        (now, target)
    }

    /// Advances axis `axis`'s effects state with the voltage applied this tick `applied_v` \[V\]
    /// and the hysteresis output the compensator's model reached `w_m` \[m\]. Call every tick,
    /// running or safe.
    #[inline]
    pub fn commit(&mut self, axis: usize, applied_v: f32, w_m: f32) {
        if let (Some(e), Some(s)) = (self.effects.get(axis), self.state.get_mut(axis)) {
            e.commit_command(s, applied_v, w_m);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::reference::{Program, Waveform};
    use piezo_core::effects::EffectParams;

    const T: f32 = 1e-4;

    fn effects(p: EffectParams) -> Effects {
        Effects::new(p, T, (0.0, 40e-6)).unwrap()
    }

    fn ramp() -> ReferenceGenerator {
        // A slow triangle: within its rising half it is a ramp of 1e-8 m per tick from −1e-5 m.
        ReferenceGenerator::new(
            Program::PerAxis([
                Waveform::Triangle {
                    offset_m: 0.0,
                    amplitude_m: 1e-5,
                    frequency_hz: 0.5,
                },
                Waveform::Triangle {
                    offset_m: 0.0,
                    amplitude_m: 2e-5,
                    frequency_hz: 0.5,
                },
            ]),
            T,
            [0.0; 2],
        )
    }

    #[test]
    fn identity_gives_no_chain() {
        let id = effects(EffectParams::default());
        assert!(InverseChain::new([id, id]).is_none());
    }

    #[test]
    fn pure_delay_targets_the_reference_ahead_and_reports_the_current_one() {
        // x: 2.5 samples; y: none (but the chain runs for both).
        let dx = effects(EffectParams {
            delay_s: 2.5 * T,
            ..EffectParams::default()
        });
        let id = effects(EffectParams::default());
        let mut chain = InverseChain::new([dx, id]).unwrap();
        assert_eq!(chain.lead_ticks(), 3);
        let mut generator = ramp();
        let r = |k: f32, amplitude: f32| -amplitude + 4.0 * amplitude * 0.5 * T * k;
        for j in 0..50 {
            let (now, target) = chain.next_targets(&mut generator);
            let jf = j as f32;
            assert!((now[0] - r(jf, 1e-5)).abs() < 1e-11, "{j}: {now:?}");
            assert!((now[1] - r(jf, 2e-5)).abs() < 1e-11, "{j}: {now:?}");
            assert!(
                (target[0] - r(jf + 2.5, 1e-5)).abs() < 1e-11,
                "{j}: {target:?}"
            );
            assert!((target[1] - r(jf, 2e-5)).abs() < 1e-11, "{j}: {target:?}");
            chain.commit(0, 10.0, target[0]);
            chain.commit(1, 10.0, target[1]);
        }
    }

    #[test]
    fn non_finite_reference_gives_nan_targets_and_never_panics() {
        let e = effects(EffectParams {
            mode_frequency_hz: 300.0,
            mode_damping: 0.1,
            delay_s: 64.0 * T,
            coupling: 0.2,
            ..EffectParams::default()
        });
        let mut chain = InverseChain::new([e, e]).unwrap();
        assert_eq!(chain.lead_ticks(), 65);
        let mut generator = ReferenceGenerator::new(Program::Streamed, T, [1e-6, 2e-6]);
        let mut held = [0; 2];
        for k in 0..400 {
            if k == 100 {
                generator.push_setpoint([f32::NAN, 1e-6]).unwrap();
            }
            if k == 101 {
                generator.push_setpoint([2e-6, 1e-6]).unwrap();
            }
            let (now, target) = chain.next_targets(&mut generator);
            chain.commit(
                0,
                5.0,
                if target[0].is_finite() {
                    target[0]
                } else {
                    0.0
                },
            );
            chain.commit(
                1,
                5.0,
                if target[1].is_finite() {
                    target[1]
                } else {
                    0.0
                },
            );
            for i in 0..2 {
                held[i] += usize::from(target[i].is_nan());
                assert!(target[i].is_nan() || target[i].is_finite());
            }
            // The first tick took samples 0..=L (L = 65), tick k takes sample k + L: the bad one,
            // dequeued at tick 100, is the reference of tick 165. It enters the history as
            // z*[101] = y*(101 + 64) at tick 100 and stays there for three ticks.
            assert_eq!(now[0].is_nan(), k == 165, "{k}");
            assert_eq!(target[0].is_nan(), (100..103).contains(&k), "{k}");
        }
        // x's NaN reaches y through the coupling (κ_y = 0.2 ≠ 0).
        assert_eq!(held, [3, 3]);
        chain.commit(7, 1.0, 1.0);
    }
}
