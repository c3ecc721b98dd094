//! The inverse of the effect chain ([`crate::effects`]) around the compensator, per tick, for two
//! axes: what the firmware's loop runs when the stage file has effects, and what
//! [`compensate_pair`] / [`compensate_single`] run over a whole reference record on the host.
//!
//! # The forward chain it inverts (per axis, command sample j, loop period T)
//! ```text
//! w[j] = H(u[j])                                   hysteresis model (the compensator's)  [m]
//! s[j] = w[j] + e·(u[j−1] − u_c)² + Σᵢ gᵢ·xᵢ[j]    even term and creep (known before u[j])
//! z[j] = M(s)[j]                                   second-order mode (unit DC gain)
//! y[k] = z(k − D) + d(k·T) + κ·z_other(k − D)      delay D [samples], drift d [m], coupling κ
//! ```
//!
//! # One tick ([`InverseChain::next_targets`], then [`InverseChain::commit`])
//! The reference is a function of the tick index that the chain samples
//! `L = M + max_axes ⌈D⌉` ticks ahead (M = h + 1 if either axis has a mode, for the mode
//! inverse's central differences over 2h + 1 samples, h = [`Effects::curvature_half_width`]: 0
//! up to 22 kHz; L ≤ 73) into a ring of [`REFERENCE_RING`] samples: at reference tick j the
//! ring holds r\[0..=j + L\] (the last [`REFERENCE_RING`] of them). Where the samples come from is
//! the caller's: a closure that yields the next reference sample pair \[m\] each time it is
//! called (the firmware's waveform generator or setpoint stream, a record on the host). With
//! q = j + M, per axis (c = the command index, the number of commands committed so far):
//!
//! 1. delay and drift: `d[q] = y*(q + D) − d((c + M + D)·T)` (linear interpolation between the
//!    ring samples q + ⌊D⌋ and q + ⌊D⌋ + 1: [`Effects::interpolate_reference`],
//!    [`Effects::drift_for_command_m`]);
//! 2. coupling: `(z*_x[q], z*_y[q]) = decouple(κ_x, κ_y, d_x[q], d_y[q])` — exact also for
//!    different delays, since each axis's output at q + D is `z[q] + κ·z_other[q]`
//!    (skipped, κ = 0, for a single axis: [`InverseChain::single`]);
//! 3. the last 2M + 1 z\* per axis, `z*[q−2M] … z*[q]`, are kept in a ring; z\* at j − h − 1,
//!    j − h, j, j + h and j + h + 1 go to [`Effects::inverse_target_w_window`] (mode, creep, even
//!    term): the target w\*\[j\] for the compensator (without a mode, M = 0, z\*\[j − 1\] and
//!    z\*\[j\]);
//! 4. after the voltage is applied, [`InverseChain::commit`] advances each axis's effects state
//!    with the voltage actually applied and the w the compensator's model reached — every tick,
//!    so that the creep, mode, delay line and drift clock follow the stage (a caller that holds
//!    its output, e.g. in a safe state, commits the held voltage).
//!
//! At the first tick the ring is filled with r\[0..=L\] and z\* before the first sample is
//! z\*\[0\] (as [`crate::effects::compensate_axis`]). The reference reported for tick j is r\[j\]:
//! the stage output the command of tick j aims at appears at sample j (after the delay).
//!
//! # Start
//! A run starts at rest at the stage's rest voltage u0 (the lower end of the output window):
//! each axis's effects state is [`EffectsState::at_rest`]`(u0)` (the creep relaxed at u0, the
//! even term of the first sample at u0) and its compensator state
//! [`CompensatorState::at_rest`]`(u0)`.
//!
//! Never panics, no allocation: ring indices are masked with a power of two, history indices are
//! constants. A non-finite reference sample gives a NaN target, and the compensator holds its
//! voltage for the up to three ticks that sample is in the history.

use crate::compensator::{CommandStatus, Compensator, CompensatorState};
use crate::effects::{decouple, Effects, EffectsState};
use crate::math::max;

/// Reference samples kept: a power of two above the largest lead (9 + 64 samples) + 1.
pub const REFERENCE_RING: usize = 128;
const RING_MASK: u32 = REFERENCE_RING as u32 - 1;
/// Desired-z samples kept per axis: a power of two at or above 2M + 1 (M ≤ 9).
const DESIRED_RING: usize = 32;
const DESIRED_MASK: u32 = DESIRED_RING as u32 - 1;

/// The inverse effect chain of two axes: settings, effect states, desired-z history and the
/// reference samples taken ahead.
#[derive(Clone, Debug)]
pub struct InverseChain {
    effects: [Effects; 2],
    state: [EffectsState; 2],
    /// κ_x, κ_y used by the decoupling (0 for a single axis).
    coupling: [f32; 2],
    /// Per axis, `desired_z_m[axis][s & DESIRED_MASK]` = z\*\[s\] \[m\] for s up to q = j + M.
    desired_z_m: [[f32; DESIRED_RING]; 2],
    /// `ring[s & RING_MASK]` = reference sample s (both axes) \[m\].
    ring: [[f32; 2]; REFERENCE_RING],
    /// Reference samples taken from the source (wrapping).
    pulled: u32,
    /// Reference index j of the next tick (wrapping).
    index: u32,
    /// L: how far ahead of tick j the reference is sampled.
    lead: u32,
    /// M: h + 1 if either axis has a mode (z\*\[j + h + 1\] is needed), else 0.
    mode_lead: u32,
    primed: bool,
}

impl InverseChain {
    /// The chain of two coupled axes (x, y) whose runs start at rest at `rest_v` \[V\]; `None`
    /// when both effects are the identity (then the reference is the compensator's target).
    pub fn new(effects: [Effects; 2], rest_v: [f32; 2]) -> Option<Self> {
        let coupling = [effects[0].params().coupling, effects[1].params().coupling];
        Self::build(effects, rest_v, coupling)
    }

    /// The chain of one axis, starting at rest at `rest_v` \[V\]: its coupling is not applied
    /// (there is no other axis). It runs in both lanes: yield `[r, r]` and use lane 0 (the
    /// targets of lane 1 are the same). `None` when the effects are the identity.
    pub fn single(effects: Effects, rest_v: f32) -> Option<Self> {
        Self::build([effects; 2], [rest_v; 2], [0.0; 2])
    }

    fn build(effects: [Effects; 2], rest_v: [f32; 2], coupling: [f32; 2]) -> Option<Self> {
        if effects.iter().all(Effects::is_identity) {
            return None;
        }
        // The mode's extra samples, h + 1 (h is the same on both axes: it follows T).
        let extra = |e: &Effects| {
            if e.has_mode() {
                e.curvature_half_width() + 1
            } else {
                0
            }
        };
        let mode_lead = effects.iter().map(extra).max().unwrap_or(0) as u32;
        // ⌈D⌉ per axis: the lead without the mode's extra samples.
        let delay_lead = effects
            .iter()
            .map(|e| e.lead_samples() - extra(e))
            .max()
            .unwrap_or(0) as u32;
        Some(Self {
            effects,
            state: [
                EffectsState::at_rest(rest_v[0]),
                EffectsState::at_rest(rest_v[1]),
            ],
            coupling,
            desired_z_m: [[0.0; DESIRED_RING]; 2],
            ring: [[0.0; 2]; REFERENCE_RING],
            pulled: 0,
            index: 0,
            lead: mode_lead + delay_lead,
            mode_lead,
            primed: false,
        })
    }

    /// L: ticks the reference is sampled ahead of the reference of the current tick.
    pub fn lead_ticks(&self) -> u32 {
        self.lead
    }

    /// The effects of the two lanes (x, y).
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
        let [kx, ky] = self.coupling;
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

    /// One tick: takes the next reference sample pair from `next_reference` (the first time,
    /// the L + 1 first ones), and returns the reference of this tick r\[j\] \[m\] and the targets
    /// w\*\[j\] \[m\] for the compensators (NaN where a reference sample is not finite).
    #[inline]
    pub fn next_targets(
        &mut self,
        mut next_reference: impl FnMut() -> [f32; 2],
    ) -> ([f32; 2], [f32; 2]) {
        let j = self.index;
        let m = self.mode_lead;
        let q = j.wrapping_add(m);
        let slot = |s: u32| (s & DESIRED_MASK) as usize;
        if self.primed {
            self.push(next_reference());
            let (zx, zy) = self.desired(q, m);
            self.desired_z_m[0][slot(q)] = zx;
            self.desired_z_m[1][slot(q)] = zy;
        } else {
            for _ in 0..=self.lead {
                self.push(next_reference());
            }
            // z* before the first sample is z*[0].
            let (x0, y0) = self.desired(j, 0);
            for back in 1..=2 * m + 2 {
                let s = j.wrapping_sub(back);
                self.desired_z_m[0][slot(s)] = x0;
                self.desired_z_m[1][slot(s)] = y0;
            }
            for ahead in 0..=m {
                let (x, y) = if ahead == 0 {
                    (x0, y0)
                } else {
                    self.desired(j.wrapping_add(ahead), ahead)
                };
                let s = j.wrapping_add(ahead);
                self.desired_z_m[0][slot(s)] = x;
                self.desired_z_m[1][slot(s)] = y;
            }
            self.primed = true;
        }
        let now = [self.sample(j, 0), self.sample(j, 1)];
        // z* at j − h − 1, j − h, j, j + h, j + h + 1 (q = j + h + 1); without a mode z*[j − 1]
        // and z*[j] (the mode's terms are absent, the samples only carry a NaN).
        let at = if m > 0 {
            [
                q.wrapping_sub(2 * m),
                q.wrapping_sub(2 * m - 1),
                j,
                q.wrapping_sub(1),
                q,
            ]
        } else {
            [j.wrapping_sub(1), j, j, j, j]
        }
        .map(slot);
        let mut target = [0.0; 2];
        for ((t, (e, s)), h) in target
            .iter_mut()
            .zip(self.effects.iter().zip(self.state.iter()))
            .zip(self.desired_z_m.iter())
        {
            *t = e.inverse_target_w_window(s, [h[at[0]], h[at[1]]], h[at[2]], [h[at[3]], h[at[4]]]);
        }
        self.index = j.wrapping_add(1);
        (now, target)
    }

    /// Advances axis `axis`'s effects state with the voltage applied this tick `applied_v` \[V\]
    /// and the hysteresis output the compensator's model reached `w_m` \[m\]. Call every tick for
    /// each axis, also while the output is held. An axis index above 1 is ignored.
    #[inline]
    pub fn commit(&mut self, axis: usize, applied_v: f32, w_m: f32) {
        if let (Some(e), Some(s)) = (self.effects.get(axis), self.state.get_mut(axis)) {
            e.commit_command(s, applied_v, w_m);
        }
    }
}

/// One axis of a feed-forward run over a record: the compensator (its window and slew limit),
/// the effects around the model, and the voltage the stage rests at before the run \[V\]
/// (the lower end of the window for the firmware and the stage file's tools).
#[derive(Clone, Copy, Debug)]
pub struct FeedforwardAxis {
    /// The inverse hysteresis compensator.
    pub compensator: Compensator,
    /// The effects around the model, at the compensator's sample period.
    pub effects: Effects,
    /// u0: the run starts at rest here \[V\].
    pub rest_v: f32,
}

/// What the compensators did over a run, summed over the axes.
#[derive(Clone, Copy, Debug, Default, PartialEq, Eq)]
pub struct FeedforwardCounts {
    /// Ticks run.
    pub ticks: usize,
    /// Samples where the window or the slew limit stopped the voltage short of the target.
    pub limited: usize,
    /// Samples with a non-finite target, held at the last voltage.
    pub held: usize,
}

/// The reference sample `k` of a record, its last sample past the end (NaN if empty).
#[inline]
fn held_sample(reference_m: &[f32], k: usize) -> f32 {
    reference_m
        .get(k)
        .or(reference_m.last())
        .copied()
        .unwrap_or(f32::NAN)
}

/// The per-tick chain over `ticks` ticks for `lanes` (1 or 2) axes of `axes`: the targets from
/// `chain` (or the reference itself without one), each lane's compensator, then the commit.
fn run(
    axes: [&FeedforwardAxis; 2],
    lanes: usize,
    mut chain: Option<InverseChain>,
    ticks: usize,
    mut next_reference: impl FnMut() -> [f32; 2],
    mut write: impl FnMut(usize, [f32; 2]) -> bool,
) -> FeedforwardCounts {
    let mut state = axes.map(|a| CompensatorState::at_rest(a.rest_v));
    let mut counts = FeedforwardCounts {
        ticks,
        ..FeedforwardCounts::default()
    };
    for j in 0..ticks {
        let (_, target) = match chain.as_mut() {
            Some(c) => c.next_targets(&mut next_reference),
            None => {
                let r = next_reference();
                (r, r)
            }
        };
        let mut u = [f32::NAN; 2];
        for (i, ((axis, state), (target, u))) in axes
            .iter()
            .zip(state.iter_mut())
            .zip(target.iter().zip(u.iter_mut()))
            .enumerate()
            .take(lanes)
        {
            let command = axis.compensator.compensate(state, *target);
            match command.status {
                CommandStatus::Tracking => {}
                CommandStatus::Limited => counts.limited += 1,
                CommandStatus::HeldInvalidReference => counts.held += 1,
            }
            if let Some(c) = chain.as_mut() {
                c.commit(
                    i,
                    command.voltage_v,
                    axis.compensator.model().output(&state.model),
                );
            }
            *u = command.voltage_v;
        }
        if !write(j, u) {
            counts.ticks = j + 1;
            break;
        }
    }
    counts
}

/// The inverse chain of two coupled axes, each from rest at its `rest_v` (`None` without
/// effects).
fn pair_chain(axes: [&FeedforwardAxis; 2]) -> Option<InverseChain> {
    InverseChain::new(
        [axes[0].effects, axes[1].effects],
        [axes[0].rest_v, axes[1].rest_v],
    )
}

/// Runs the firmware's per-tick feed-forward of two coupled axes over a reference record:
/// tick j takes r\[j\] of both axes (`reference_m` \[m\], held at its last sample past the end,
/// which the chain's lead reads), [`InverseChain`] (lead ring, drift, decoupling, mode inverse,
/// creep and even term), each axis's compensator (window and slew limit) from rest at its
/// `rest_v`, and the commit; writes the commanded voltages \[V\] to `u_out_v`. Runs
/// `min` of the four lengths ticks. Without effects the target is the reference (as in the
/// firmware).
pub fn compensate_pair(
    axes: [&FeedforwardAxis; 2],
    reference_m: [&[f32]; 2],
    u_out_v: [&mut [f32]; 2],
) -> FeedforwardCounts {
    let [rx, ry] = reference_m;
    let [ux, uy] = u_out_v;
    let ticks = rx.len().min(ry.len()).min(ux.len()).min(uy.len());
    let chain = pair_chain(axes);
    let mut k = 0;
    let next = || {
        let s = [held_sample(rx, k), held_sample(ry, k)];
        k += 1;
        s
    };
    run(axes, 2, chain, ticks, next, |j, u| {
        if let (Some(x), Some(y)) = (ux.get_mut(j), uy.get_mut(j)) {
            (*x, *y) = (u[0], u[1]);
        }
        true
    })
}

/// [`compensate_pair`] for one axis (no coupling): `min(reference_m.len(), u_out_v.len())` ticks.
pub fn compensate_single(
    axis: &FeedforwardAxis,
    reference_m: &[f32],
    u_out_v: &mut [f32],
) -> FeedforwardCounts {
    let ticks = reference_m.len().min(u_out_v.len());
    let chain = InverseChain::single(axis.effects, axis.rest_v);
    let mut k = 0;
    let next = || {
        let r = held_sample(reference_m, k);
        k += 1;
        [r, r]
    };
    run([axis, axis], 1, chain, ticks, next, |j, u| {
        if let Some(x) = u_out_v.get_mut(j) {
            *x = u[0];
        }
        true
    })
}

/// When the feed-forward of a reference played in a loop has settled
/// ([`compensate_periodic_pair`]).
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PeriodicSettings {
    /// Fewest whole periods run before the period taken (the hysteresis leaves its
    /// first-loading branch in the first).
    pub min_periods: usize,
    /// Most whole periods run before the period taken, settled or not.
    pub max_periods: usize,
    /// The period is settled when no command moved more than this from the period before \[V\].
    pub tolerance_v: f32,
}

/// How the feed-forward played in a loop settled.
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct PeriodicSettling {
    /// Whole periods run before the period taken.
    pub periods: usize,
    /// `max_j |u_p[j] − u_{p−1}[j]|` over the axes: how far the period taken moved from the one
    /// before \[V\] (a stage file with drift or creep never settles below the drift's share).
    pub change_v: f32,
    /// Whether `change_v` is within the tolerance (else `max_periods` was reached).
    pub settled: bool,
    /// What the compensators did over the whole run.
    pub counts: FeedforwardCounts,
}

/// The period the feed-forward of a reference played in a loop settles to: the chain of
/// [`compensate_pair`] from rest over `reference_m` repeated (one period, P = the shortest of the
/// four lengths; the chain's look-ahead reads the next period), run period by period until
/// period p ≥ `min_periods` moved no command more than `tolerance_v` from period p − 1, or p =
/// `max_periods`; period p is written to `u_out_v`. Without settling, a table cut from the
/// first periods jumps at its wrap by what the hysteresis state still moves per period (a
/// Bouc-Wen loop forgets its start only geometrically, by exp(−(β ± γ)·Δu) per branch).
pub fn compensate_periodic_pair(
    axes: [&FeedforwardAxis; 2],
    reference_m: [&[f32]; 2],
    settings: PeriodicSettings,
    u_out_v: [&mut [f32]; 2],
) -> PeriodicSettling {
    let [rx, ry] = reference_m;
    let [ux, uy] = u_out_v;
    let period = rx.len().min(ry.len()).min(ux.len()).min(uy.len());
    let chain = pair_chain(axes);
    let mut k = 0;
    let next = || {
        let s = if period == 0 {
            [f32::NAN; 2]
        } else {
            [rx[k % period], ry[k % period]]
        };
        k += 1;
        s
    };
    settle(axes, chain, period, settings, next, &mut [ux, uy])
}

/// [`compensate_periodic_pair`] for one axis (no coupling).
pub fn compensate_periodic_single(
    axis: &FeedforwardAxis,
    reference_m: &[f32],
    settings: PeriodicSettings,
    u_out_v: &mut [f32],
) -> PeriodicSettling {
    let period = reference_m.len().min(u_out_v.len());
    let chain = InverseChain::single(axis.effects, axis.rest_v);
    let mut k = 0;
    let next = || {
        let r = if period == 0 {
            f32::NAN
        } else {
            reference_m[k % period]
        };
        k += 1;
        [r, r]
    };
    settle([axis, axis], chain, period, settings, next, &mut [u_out_v])
}

/// The period loop of [`compensate_periodic_pair`]: one table per lane in `out` (1 or 2), each
/// at least `period` long.
fn settle(
    axes: [&FeedforwardAxis; 2],
    chain: Option<InverseChain>,
    period: usize,
    settings: PeriodicSettings,
    next_reference: impl FnMut() -> [f32; 2],
    out: &mut [&mut [f32]],
) -> PeriodicSettling {
    let lanes = out.len().min(2);
    if period == 0 {
        return PeriodicSettling::default();
    }
    let last = settings.max_periods.max(settings.min_periods);
    let ticks = (last + 1).saturating_mul(period);
    let mut change = 0.0f32;
    let mut result = PeriodicSettling::default();
    let counts = run(axes, lanes, chain, ticks, next_reference, |k, u| {
        let (p, j) = (k / period, k % period);
        if j == 0 {
            change = 0.0;
        }
        for (table, &v) in out.iter_mut().zip(u.iter()) {
            let Some(entry) = table.get_mut(j) else {
                continue;
            };
            if p > 0 {
                let moved = libm::fabsf(v - *entry);
                // A NaN (held reference) counts as unsettled.
                change = if moved.is_nan() {
                    f32::INFINITY
                } else {
                    max(change, moved)
                };
            }
            *entry = v;
        }
        if j + 1 < period {
            return true;
        }
        let settled = p >= settings.min_periods && p > 0 && change <= settings.tolerance_v;
        result.periods = p;
        result.change_v = change;
        result.settled = settled;
        !settled && p < last
    });
    result.counts = counts;
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::effects::{compensate_axis, EffectParams};
    use crate::{CompensatorSettings, StaticMap, StaticModel};

    const T: f32 = 1e-4;

    fn effects(p: EffectParams) -> Effects {
        Effects::new(
            p,
            T,
            crate::effects::OperatingRange {
                input_v: (0.0, 120.0),
                output_m: (0.0, 40e-6),
            },
        )
        .unwrap()
    }

    /// A rising ramp of 1e-8 m per tick from −`amplitude` \[m\].
    fn ramp(amplitude: f32) -> impl FnMut() -> [f32; 2] {
        let mut k = 0;
        move || {
            let r = [amplitude, 2.0 * amplitude].map(|a| -a + 2.0 * a * T * k as f32);
            k += 1;
            r
        }
    }

    #[test]
    fn identity_gives_no_chain() {
        let id = effects(EffectParams::default());
        assert!(InverseChain::new([id, id], [0.0; 2]).is_none());
        assert!(InverseChain::single(id, 0.0).is_none());
    }

    #[test]
    fn pure_delay_targets_the_reference_ahead_and_reports_the_current_one() {
        // x: 2.5 samples; y: none (but the chain runs for both).
        let dx = effects(EffectParams {
            delay_s: 2.5 * T,
            ..EffectParams::default()
        });
        let id = effects(EffectParams::default());
        let mut chain = InverseChain::new([dx, id], [0.0; 2]).unwrap();
        assert_eq!(chain.lead_ticks(), 3);
        let mut source = ramp(1e-5);
        let r = |k: f32, amplitude: f32| -amplitude + 2.0 * amplitude * T * k;
        for j in 0..50 {
            let (now, target) = chain.next_targets(&mut source);
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
        let mut chain = InverseChain::new([e, e], [5.0; 2]).unwrap();
        assert_eq!(chain.lead_ticks(), 65);
        let mut pulled = 0;
        let mut source = || {
            pulled += 1;
            // Sample 165 (the 166th pulled) is NaN on x.
            if pulled == 166 {
                [f32::NAN, 1e-6]
            } else {
                [1e-6, 1e-6]
            }
        };
        let mut held = [0; 2];
        for k in 0..400 {
            let (now, target) = chain.next_targets(&mut source);
            for (i, t) in target.iter().enumerate() {
                chain.commit(i, 5.0, if t.is_finite() { *t } else { 0.0 });
                held[i] += usize::from(t.is_nan());
            }
            // The first tick took samples 0..=L (L = 65), tick k takes sample k + L: the bad one is
            // taken at tick 100 and is the reference of tick 165. It enters the history as
            // z*[101] = y*(101 + 64) at tick 100 and stays there for three ticks.
            assert_eq!(now[0].is_nan(), k == 165, "{k}");
            assert_eq!(target[0].is_nan(), (100..103).contains(&k), "{k}");
        }
        // x's NaN reaches y through the coupling (κ_y = 0.2 ≠ 0).
        assert_eq!(held, [3, 3]);
        chain.commit(7, 1.0, 1.0);
    }

    fn compensator() -> Compensator {
        let bw = crate::fixtures::x_stack(1.0, 1e6);
        let map = StaticMap {
            k1_m_per_v: 3.574e-7,
            k2_m_per_h: -3.574e-7,
            offset_m: 0.0,
        };
        let settings = CompensatorSettings {
            limits: crate::Limits::new(0.0, 120.0, 1e5),
            sample_period_s: T,
        };
        Compensator::new(StaticModel::new(bw, map).unwrap(), settings).unwrap()
    }

    /// At 50 kHz the mode's inverse spreads a triangle's corner over 5 ticks: the compensator's
    /// slew limit (1e5 V/s, 2 V per tick) never cuts the drive, and the stage (the forward chain
    /// with the same mode) follows the triangle at least 5× closer than with the one-tick
    /// curvature ([`Effects::inverse_target_w`]), whose corner pulse (1.3 µm of w in one tick,
    /// more than 2 V) the limit cuts short.
    #[test]
    fn at_a_fast_rate_the_mode_inverse_keeps_the_corners_impulse_within_the_slew_limit() {
        const T5: f32 = 2e-5;
        const N: usize = 2000;
        let compensator = {
            let c = compensator();
            let settings = CompensatorSettings {
                sample_period_s: T5,
                ..c.settings()
            };
            Compensator::new(*c.model(), settings).unwrap()
        };
        let effects = Effects::new(
            EffectParams {
                mode_frequency_hz: 2197.0,
                mode_damping: 0.03,
                ..EffectParams::default()
            },
            T5,
            crate::effects::OperatingRange {
                input_v: (0.0, 120.0),
                output_m: (0.0, 40e-6),
            },
        )
        .unwrap();
        assert_eq!(effects.curvature_half_width(), 2);
        // 50 Hz between 4 and 29 µm (1000 ticks a period), from its low end.
        let mut reference = [0.0f32; N];
        for (k, r) in reference.iter_mut().enumerate() {
            let p = (k % 1000) as f32 / 1000.0;
            *r = 4e-6 + 25e-6 * if p < 0.5 { 2.0 * p } else { 2.0 - 2.0 * p };
        }
        let rest = CompensatorState::at_rest(11.2);
        // (ticks the slew limit cut, RMS error [m]) over the second period.
        let score = |u: &[f32; N], limited: usize| {
            let mut y = [0.0f32; N];
            crate::effects::simulate_axis(compensator.model(), rest.model, &effects, u, &mut y);
            let sum: f32 = (N / 2..N).map(|k| (y[k] - reference[k]).powi(2)).sum();
            (limited, libm::sqrtf(sum / (N / 2) as f32))
        };
        // The chain (2h + 1 = 5 samples).
        let mut chain = InverseChain::single(effects, 11.2).unwrap();
        assert_eq!(chain.lead_ticks(), 3);
        let (mut state, mut u, mut limited) = (rest, [0.0f32; N], 0);
        let mut k = 0;
        for (j, u) in u.iter_mut().enumerate() {
            let (_, target) = chain.next_targets(|| {
                let r = held_sample(&reference, k);
                k += 1;
                [r, r]
            });
            let command = compensator.compensate(&mut state, target[0]);
            limited += usize::from(j >= N / 2 && command.status == CommandStatus::Limited);
            chain.commit(
                0,
                command.voltage_v,
                compensator.model().output(&state.model),
            );
            *u = command.voltage_v;
        }
        // The record chain of the effects module reads the same window from the slice.
        let mut record = [0.0f32; N];
        crate::effects::compensate_axis(&compensator, rest, &effects, &reference, &mut record);
        assert_eq!(u, record);
        let windowed = score(&u, limited);
        // The curvature in one tick.
        let (mut state, mut u, mut limited) = (rest, [0.0f32; N], 0);
        let mut effects_state = EffectsState::at_rest(11.2);
        for (j, u) in u.iter_mut().enumerate() {
            let z = |i: usize| effects.desired_z_m(&reference, i);
            let target =
                effects.inverse_target_w(&effects_state, z(j.saturating_sub(1)), z(j), z(j + 1));
            let command = compensator.compensate(&mut state, target);
            limited += usize::from(j >= N / 2 && command.status == CommandStatus::Limited);
            let w = compensator.model().output(&state.model);
            effects.commit_command(&mut effects_state, command.voltage_v, w);
            *u = command.voltage_v;
        }
        let one_tick = score(&u, limited);
        extern crate std;
        std::println!("windowed {windowed:?}, one tick {one_tick:?}");
        assert_eq!(windowed.0, 0, "{windowed:?}");
        assert!(one_tick.0 >= 2, "{one_tick:?}");
        assert!(windowed.1 < 0.2 * one_tick.1, "{windowed:?} {one_tick:?}");
    }

    fn triangle(n: usize) -> [f32; 600] {
        let mut r = [0.0; 600];
        for (k, r) in r.iter_mut().enumerate().take(n) {
            let p = (k % 200) as f32 / 200.0;
            let tri = if p < 0.5 { 2.0 * p } else { 2.0 - 2.0 * p };
            *r = 4e-6 + 25e-6 * tri;
        }
        r
    }

    #[test]
    fn single_axis_run_is_the_record_chain_of_the_effects_module() {
        // Two independent ways to read the reference ahead: the ring here, slices in
        // `compensate_axis`. Same voltages, bit for bit.
        for p in [
            EffectParams::default(),
            EffectParams {
                creep_gain_m_per_v: [1e-8, 0.0, 0.0],
                creep_time_constant_s: [0.2, 0.0, 0.0],
                even_coefficient_m_per_v2: 1e-10,
                even_center_v: 60.0,
                delay_s: 2.5 * T,
                drift_rate_m_per_s: -2e-7,
                mode_frequency_hz: 800.0,
                mode_damping: 0.2,
                ..EffectParams::default()
            },
        ] {
            let axis = FeedforwardAxis {
                compensator: compensator(),
                effects: effects(p),
                rest_v: 0.0,
            };
            let reference = triangle(600);
            let mut u = [0.0; 600];
            let counts = compensate_single(&axis, &reference, &mut u);
            let mut expected = [0.0; 600];
            compensate_axis(
                &axis.compensator,
                CompensatorState::at_rest(0.0),
                &axis.effects,
                &reference,
                &mut expected,
            );
            assert_eq!(counts.ticks, 600);
            assert_eq!(counts.held, 0);
            assert_eq!(u, expected);
        }
    }

    #[test]
    fn a_looped_reference_settles_to_a_period_that_closes_at_its_wrap() {
        extern crate std;
        let axis = FeedforwardAxis {
            compensator: compensator(),
            effects: effects(EffectParams {
                mode_frequency_hz: 800.0,
                mode_damping: 0.2,
                delay_s: 1.5 * T,
                ..EffectParams::default()
            }),
            rest_v: 0.0,
        };
        let one = triangle(200);
        let reference = &one[..200];
        let settings = PeriodicSettings {
            min_periods: 1,
            max_periods: 60,
            tolerance_v: 1e-4,
        };
        let mut table = [0.0f32; 200];
        let settled = compensate_periodic_single(&axis, reference, settings, &mut table);
        assert!(settled.settled, "{settled:?}");
        assert!(settled.change_v <= 1e-4, "{settled:?}");
        assert_eq!(settled.counts.ticks, (settled.periods + 1) * 200);
        // The same chain over the record repeated, read as a plain slice: the periods after the
        // one taken repeat it, and the first period (from rest) does not.
        let periods = settled.periods + 3;
        let looped: std::vec::Vec<f32> = (0..periods * 200).map(|k| reference[k % 200]).collect();
        let mut u = std::vec![0.0f32; periods * 200];
        compensate_single(&axis, &looped, &mut u);
        let moved = |p: usize| {
            (0..200)
                .map(|j| (u[p * 200 + j] - table[j]).abs())
                .fold(0.0f32, f32::max)
        };
        assert_eq!(moved(settled.periods), 0.0);
        assert!(
            moved(settled.periods + 1) <= 2e-4,
            "{}",
            moved(settled.periods + 1)
        );
        // The first period from rest is not the loop: cut there, the table would jump at its
        // wrap by what the hysteresis still moves per period.
        assert!(moved(0) > 100.0 * settings.tolerance_v, "{}", moved(0));
        // A cap below what settling needs: the change is reported, not hidden.
        let capped = compensate_periodic_single(
            &axis,
            reference,
            PeriodicSettings {
                max_periods: 1,
                ..settings
            },
            &mut table,
        );
        assert!(!capped.settled && capped.change_v > 1e-4, "{capped:?}");
        assert_eq!(capped.periods, 1);
        // The pair runs each uncoupled axis as the single axis does.
        let (mut tx, mut ty) = ([0.0f32; 200], [0.0f32; 200]);
        let pair = compensate_periodic_pair(
            [&axis, &axis],
            [reference, reference],
            settings,
            [&mut tx, &mut ty],
        );
        let mut single = [0.0f32; 200];
        compensate_periodic_single(&axis, reference, settings, &mut single);
        assert_eq!((tx, ty, pair.periods), (single, single, settled.periods));
    }

    #[test]
    fn pair_without_coupling_runs_each_axis_alone() {
        let e = effects(EffectParams {
            creep_gain_m_per_v: [1e-8, 0.0, 0.0],
            creep_time_constant_s: [0.2, 0.0, 0.0],
            delay_s: 2.0 * T,
            ..EffectParams::default()
        });
        let axis = FeedforwardAxis {
            compensator: compensator(),
            effects: e,
            rest_v: 0.0,
        };
        let (rx, ry) = (triangle(600), triangle(300));
        let (mut ux, mut uy) = ([0.0; 600], [0.0; 600]);
        let counts = compensate_pair([&axis, &axis], [&rx, &ry], [&mut ux, &mut uy]);
        assert_eq!(counts.ticks, 600);
        let (mut sx, mut sy) = ([0.0; 600], [0.0; 600]);
        compensate_single(&axis, &rx, &mut sx);
        compensate_single(&axis, &ry, &mut sy);
        assert_eq!((ux, uy), (sx, sy));
    }

    #[test]
    fn coupling_is_inverted_by_the_pair() {
        // With coupling on both axes, y's command must differ from its uncoupled command by the
        // part of x's motion it has to take out.
        let coupled = |kappa: f32| FeedforwardAxis {
            compensator: compensator(),
            effects: effects(EffectParams {
                coupling: kappa,
                ..EffectParams::default()
            }),
            rest_v: 0.0,
        };
        let (x, y) = (coupled(0.02), coupled(-0.015));
        let rx = triangle(600);
        let ry = [15e-6; 600];
        let (mut ux, mut uy) = ([0.0; 600], [0.0; 600]);
        compensate_pair([&x, &y], [&rx, &ry], [&mut ux, &mut uy]);
        let mut alone = [0.0; 600];
        compensate_single(&y, &ry, &mut alone);
        // y* = z_y − 0.015·z_x: where x is high, y must be driven higher than alone.
        let k = 100; // the triangle's peak (29 µm)
        assert!(uy[k] > alone[k] + 0.5, "{} vs {}", uy[k], alone[k]);
    }
}
