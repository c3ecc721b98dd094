//! The feedback servo on the position sensor, on top of the inverse feedforward: the hybrid
//! controller of a sensor-equipped stage. The feedforward ([`crate::Compensator`], with the
//! inverse effect chain around it) removes what the model knows — hysteresis, the static gain —
//! so the stage tracks fast references; the servo removes what no model captures — creep, drift,
//! load changes, a model that is slightly off — at the frequencies its loop gain reaches.
//!
//! # Control law (per axis, per tick k, loop period T)
//! ```text
//! e[k]   = r[k] − y[k]                                   error: reference − measured [m]
//! e_f[k] = N(z)·L(z)·e[k]                                low-pass L, then notch N
//! c*[k]  = c[k−1] + (kp + ki·T)·e_f[k] − kp·e_f[k−1]      PI, backward Euler [V]
//! u[k]   = sat_k(u_ff[k] + c*[k])                        the sum, limited
//! c[k]   = u[k] − u_ff[k]                                stored: anti-windup
//! ```
//! `sat_k` limits to the axis's output window `[u_min, u_max]` ([`crate::Limits`]) and to the
//! slew limit, `|u[k] − u[k−1]| ≤ S·T` (the window wins when the last output lies outside it).
//! Storing the *limited* correction as the PI's last output is the anti-windup: at a limit the
//! integrator holds what was actually applied instead of winding up, so it leaves the limit as
//! soon as the error changes sign, and a feedforward near the window's edge leaves the servo only
//! the room that is left. Sign convention: the correction is in volts and is *added* to the
//! feedforward voltage; for a stage whose displacement rises with voltage (dy/du > 0) the gains
//! are positive, for dy/du < 0 both are negative.
//!
//! # Filters (idsp biquads, direct form I, coefficients computed once in f64)
//! Biquads `y0 = b0·x0 + b1·x1 + b2·x2 + a1·y1 + a2·y2` (idsp's sign of a1, a2), from the RBJ
//! cookbook with `w0 = 2π·f/f_s`, `α = sin w0 / (2Q)` (`idsp::iir::coefficients::Filter`):
//! ```text
//! low-pass  L(z) = (1 − cos w0)/2 · (1 + 2z⁻¹ + z⁻²) / ((1 + α) − 2cos w0·z⁻¹ + (1 − α)z⁻²)
//! notch     N(z) = (1 − 2cos w0·z⁻¹ + z⁻²)            / ((1 + α) − 2cos w0·z⁻¹ + (1 − α)z⁻²)
//! PI        C(z) = ((kp + ki·T) − kp·z⁻¹) / (1 − z⁻¹)   (idsp::iir::pid::Builder, order I)
//! ```
//! The notch has zero gain exactly at its frequency and a −3 dB width of f/Q; both filters have
//! unit gain at DC. A frequency of 0 leaves that filter out (identity).
//!
//! A notch whose poles sit at f_p above its centre f_z (`notch_pole_frequency_hz`) is a notch
//! with lead: the bilinear transform, prewarped at f_z so that its zero stays exactly there, of
//! ```text
//! N(s) = (ω_p/ω_z)² · (s² + ω_z²) / (s² + (ω_p/Q)·s + ω_p²)       ω = 2π·f
//! ```
//! Unit gain at DC, zero at f_z, (ω_p/ω_z)² far above f_p, and a phase lead of up to 180° between
//! f_z and f_p. Beside a lightly damped mode it removes the mode's peak from the loop and, above
//! it, turns the loop's phase back, so a fast loop can hold the mode by phase (active damping:
//! the loop gain near the mode stays above 1 with the phase far from −180°) instead of by gain
//! alone. With f_p = f_z it is the notch above.
//!
//! # Modes and bumpless switching ([`ServoMode`], [`ServoState::set_mode`])
//! - open loop and feedforward: `u = sat(u_ff + o)`: the caller's feedforward passes through
//!   (open loop: the linear map `u_min + (r − y_rest)/g`; feedforward: the compensator), the
//!   servo only keeps its filters running on the error, so that feedback can take over smoothly;
//! - feedback: `u_ff = 0`, the PI produces the whole voltage;
//! - feedforward + feedback: the law above.
//!
//! At the first tick after a mode change (and the first tick of a run) the output is the last
//! output, `c = u[k−1] − u_ff[k]`: with feedback, the PI's output history takes that value (a
//! direct-form-I filter stores only its inputs and outputs, so this is a complete, jump-free
//! hand-over, and the error history keeps the proportional term from kicking); without feedback
//! the difference `o` decays with `transfer_time_constant_s`, `o[k] = o[k−1]·exp(−T/τ)`.
//!
//! # Per-sample path
//! [`Servo::step`] never panics, never allocates, never returns NaN and never leaves the window.
//! A non-finite feedforward holds the last output; a non-finite reference or measurement holds
//! the correction (with feedback) and leaves the filter states as they were.
//!
//! # Tuning ([`tune`])
//! From the stage's dynamics — the largest small-signal gain dy/du of its identified model and its
//! first mode — by loop shaping with a stated phase margin; see [`tune`] for the rule.

use crate::compensator::CompensatorSettings;
use crate::error::{finite, positive, ParamError};
use crate::math::{clamp, max, min};
use crate::static_model::StaticModel;
use crate::Limits;
use dsp_process::SplitProcess;
use idsp::iir::{coefficients::Filter, pid, Biquad, DirectForm1};
use idsp::Build;

/// Largest proportional loop gain |kp·g| accepted (g the stage's gain dy/du \[m/V\]): a loop with a
/// tick of latency is unstable at |kp·g| ≥ 1 without filtering, and the low-pass and notch buy at
/// most a decade of it (tuned servos stay below 1).
pub const MAX_PROPORTIONAL_LOOP_GAIN: f32 = 10.0;
/// Largest integral gain per tick |ki·g|·T accepted: the integrator alone crosses unity gain at
/// |ki·g|/2π, which must stay below the Nyquist frequency 1/(2T), i.e. |ki·g|·T < π.
pub const MAX_INTEGRAL_GAIN_PER_TICK: f32 = core::f32::consts::PI;

/// Highest filter frequency accepted, as a fraction of the loop rate.
pub const MAX_FILTER_FRACTION: f32 = 0.45;

/// How the tick combines feedforward and feedback.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ServoMode {
    /// The caller's linear feedforward (no model, no feedback): the uncompensated baseline.
    OpenLoop,
    /// The caller's inverse feedforward (the compensator) alone.
    Feedforward,
    /// The PI on the sensor alone; the feedforward is ignored.
    Feedback,
    /// The inverse feedforward plus the PI's correction.
    FeedforwardFeedback,
}

impl ServoMode {
    /// The four modes, in the order of the benchmark's table.
    pub const ALL: [Self; 4] = [
        Self::OpenLoop,
        Self::Feedforward,
        Self::Feedback,
        Self::FeedforwardFeedback,
    ];

    /// Name as written in reports: `open-loop`, `feedforward`, `feedback`, `feedforward+feedback`.
    pub fn name(self) -> &'static str {
        match self {
            Self::OpenLoop => "open-loop",
            Self::Feedforward => "feedforward",
            Self::Feedback => "feedback",
            Self::FeedforwardFeedback => "feedforward+feedback",
        }
    }

    /// Whether the PI's correction is applied.
    pub fn feedback(self) -> bool {
        matches!(self, Self::Feedback | Self::FeedforwardFeedback)
    }

    /// Whether the caller's feedforward voltage is added.
    pub fn feedforward(self) -> bool {
        !matches!(self, Self::Feedback)
    }

    /// Whether the caller's feedforward should be the inverse model (the compensator) rather than
    /// the linear map: every mode but open loop.
    pub fn model_feedforward(self) -> bool {
        !matches!(self, Self::OpenLoop)
    }
}

/// Raw servo parameters: the stage file's `[x.servo]` table (not yet validated).
#[derive(Debug, Clone, Copy, PartialEq)]
#[cfg_attr(feature = "serde", derive(serde::Serialize, serde::Deserialize))]
#[cfg_attr(feature = "serde", serde(deny_unknown_fields))]
pub struct ServoParams {
    /// kp: proportional gain \[V/m\]; 0, or the sign of `ki_v_per_m_s`.
    pub kp_v_per_m: f32,
    /// ki: integral gain \[V/(m·s)\]; nonzero, the sign of the stage's dy/du.
    pub ki_v_per_m_s: f32,
    /// Low-pass corner \[Hz\]: 0 for none, else in (0, 0.45 / sample period).
    pub lowpass_frequency_hz: f32,
    /// Low-pass Q (1/√2: Butterworth), > 0.
    pub lowpass_q: f32,
    /// Notch centre \[Hz\] (the stage's first mode): 0 for none, else in (0, 0.45 / sample period).
    pub notch_frequency_hz: f32,
    /// Notch Q, > 0: of its poles (1/(2ζ_p)); for a plain notch also centre / −3 dB width.
    pub notch_q: f32,
    /// The notch's poles \[Hz\]: 0 (the default) puts them at its centre, a plain notch; a
    /// higher frequency makes it a notch with lead, whose gain rises by (f_p/f_notch)² above
    /// f_p and leads by up to 180° between the two, in (0, 0.45 / sample period). Needs a notch.
    #[cfg_attr(feature = "serde", serde(default))]
    pub notch_pole_frequency_hz: f32,
    /// τ with which a mode without feedback fades out the difference found at a mode change \[s\], > 0.
    pub transfer_time_constant_s: f32,
}

/// The validated servo of one axis: filter and PI coefficients, limits. Settings only; the
/// run-time values are in [`ServoState`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Servo {
    params: ServoParams,
    /// `[b0, b1, b2, a1, a2]`, idsp's sign convention.
    lowpass: [f32; 5],
    notch: [f32; 5],
    pi: [f32; 5],
    /// The axis's output window and slew limit (the compensator's, [`CompensatorSettings`]).
    limits: Limits,
    /// S·T \[V\] (+∞: no slew limit).
    slew_step_v: f32,
    /// exp(−T/τ_transfer).
    transfer_decay: f32,
    sample_period_s: f32,
}

/// What the servo did with a tick.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum ServoStatus {
    /// The output is the feedforward plus the correction (or the feedforward alone).
    Tracking,
    /// The window or the slew limit stopped the sum; the correction was limited (anti-windup).
    Limited,
    /// A non-finite input: the last output (non-finite feedforward) or the last correction
    /// (non-finite reference or measurement, with feedback) is held.
    Held,
}

/// One tick's output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServoOutput {
    /// The voltage to apply \[V\]: inside the window and the slew limit.
    pub voltage_v: f32,
    /// The part of it that is not feedforward, `u − u_ff` \[V\] (`u` itself in feedback mode).
    pub correction_v: f32,
    /// What happened.
    pub status: ServoStatus,
}

/// A direct-form-I history: last two inputs, last two outputs.
#[derive(Debug, Clone, Copy, PartialEq, Default)]
struct History {
    x: [f32; 2],
    y: [f32; 2],
}

impl History {
    #[inline(always)]
    fn process(&mut self, ba: &[f32; 5], x0: f32) -> f32 {
        let mut state = DirectForm1 {
            x: self.x,
            y: [self.y],
        };
        let y0 = Biquad { ba: *ba }.process(&mut state, x0);
        self.x = state.x;
        self.y = state.y[0];
        y0
    }
}

/// The servo's run-time state: mode, filter histories, last output.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ServoState {
    mode: ServoMode,
    /// The next tick hands over from the last output (a mode change, the first tick).
    transfer: bool,
    lowpass: History,
    notch: History,
    /// Inputs: filtered errors; outputs: the (limited) corrections.
    pi: History,
    output_v: f32,
}

impl ServoState {
    /// A run that starts at rest with `voltage_v` applied, in `mode`: the first tick hands over
    /// from `voltage_v`.
    pub fn at_rest(voltage_v: f32, mode: ServoMode) -> Self {
        Self {
            mode,
            transfer: true,
            lowpass: History::default(),
            notch: History::default(),
            pi: History::default(),
            output_v: voltage_v,
        }
    }

    /// Switches the mode; the next tick hands over bumplessly from the last output.
    pub fn set_mode(&mut self, mode: ServoMode) {
        if mode != self.mode {
            self.mode = mode;
            self.transfer = true;
        }
    }

    /// The next tick hands over bumplessly from the last output, in the same mode, as after a
    /// mode change: for a feedforward whose source changes under a running servo (the
    /// compensator's command replaced by a learned table, or back) by an amount the caller does
    /// not know. With feedback the PI's output history becomes `c = u[k−1] − u_ff[k]`.
    pub fn hand_over(&mut self) {
        self.transfer = true;
    }

    /// The feedforward steps by `delta_v` \[V\] at the next tick by a change the servo should
    /// not answer: a new learned voltage table that has taken over the correction the servo was
    /// holding (Δ = new − old table entry at that tick). In feedforward + feedback the stored correction
    /// drops by as much, `c ← c − Δ`, so that the sum `u = u_ff + c` continues without a jump
    /// and without a held tick, and the PI goes on from there; in the other modes (no
    /// feedback, or feedback alone, which ignores the feedforward), or for a non-finite Δ,
    /// nothing changes.
    pub fn take_over(&mut self, delta_v: f32) {
        if self.mode == ServoMode::FeedforwardFeedback && delta_v.is_finite() {
            self.pi.y[0] -= delta_v;
            self.pi.y[1] -= delta_v;
        }
    }

    /// The mode in force.
    pub fn mode(&self) -> ServoMode {
        self.mode
    }

    /// The last output \[V\].
    pub fn output_v(&self) -> f32 {
        self.output_v
    }

    /// The last correction `u − u_ff` \[V\].
    pub fn correction_v(&self) -> f32 {
        self.pi.y[0]
    }
}

/// Checks a filter frequency: 0 (none) or in (0, 0.45·f_s).
fn filter_frequency(field: &'static str, hz: f32, sample_period_s: f32) -> Result<f32, ParamError> {
    finite(field, hz)?;
    if hz == 0.0 || (hz > 0.0 && hz < MAX_FILTER_FRACTION / sample_period_s) {
        Ok(hz)
    } else {
        Err(ParamError::OutOfRange {
            field,
            value: hz,
            requirement: "0 (none) or in (0, 0.45 / sample_period_s)",
        })
    }
}

/// Biquad coefficients `[b0, b1, b2, a1, a2]` of an RBJ filter at `hz` (identity when 0).
fn rbj(hz: f32, q: f32, sample_period_s: f32, notch: bool) -> [f32; 5] {
    if hz == 0.0 {
        return Biquad::<f32>::IDENTITY.ba;
    }
    let mut f = Filter::<f64>::default();
    f.frequency(f64::from(hz), 1.0 / f64::from(sample_period_s))
        .q(f64::from(q));
    let ba = if notch { f.notch() } else { f.lowpass() };
    Biquad::<f32>::from(ba).ba
}

/// Coefficients `[b0, b1, b2, a1, a2]` (idsp's sign of a1, a2) of the notch with lead
/// `N(s) = (ω_p/ω_z)²·(s² + ω_z²)/(s² + (ω_p/Q)s + ω_p²)`, bilinear with prewarping at ω_z
/// (module doc): with `K = ω_z / tan(ω_z·T/2)`,
/// `B = (ω_p/ω_z)²·[K² + ω_z², 2ω_z² − 2K², K² + ω_z²]`,
/// `A = [K² + K·ω_p/Q + ω_p², 2ω_p² − 2K², K² − K·ω_p/Q + ω_p²]`, normalised by `A[0]`.
fn notch_with_lead(zero_hz: f32, pole_hz: f32, q: f32, sample_period_s: f32) -> [f32; 5] {
    let t = f64::from(sample_period_s);
    let wz = 2.0 * core::f64::consts::PI * f64::from(zero_hz);
    let wp = 2.0 * core::f64::consts::PI * f64::from(pole_hz);
    let k = wz / libm::tan(wz * t / 2.0);
    let (k2, wz2, wp2) = (k * k, wz * wz, wp * wp);
    let damping = k * wp / f64::from(q);
    let a0 = k2 + damping + wp2;
    let gain = wp2 / wz2 / a0;
    [
        (gain * (k2 + wz2)) as f32,
        (gain * (2.0 * wz2 - 2.0 * k2)) as f32,
        (gain * (k2 + wz2)) as f32,
        (-(2.0 * wp2 - 2.0 * k2) / a0) as f32,
        (-(k2 - damping + wp2) / a0) as f32,
    ]
}

impl Servo {
    /// Validates `params` for a loop with the output window, slew limit and sample period of
    /// `settings` (the compensator's of the same axis, [`CompensatorSettings::check_slew`])
    /// around a stage of gain `gain_m_per_v` = g = dy/du \[m/V\] (its sign is the stage's; the
    /// firmware passes the first-loading secant gain over the window). The gains are checked as
    /// loop gains: ki·g > 0 (negative feedback), |kp·g| ≤ [`MAX_PROPORTIONAL_LOOP_GAIN`] and
    /// |ki·g|·T ≤ [`MAX_INTEGRAL_GAIN_PER_TICK`].
    pub fn new(
        params: ServoParams,
        settings: CompensatorSettings,
        gain_m_per_v: f32,
    ) -> Result<Self, ParamError> {
        settings.check_slew()?;
        let CompensatorSettings {
            limits,
            sample_period_s: t,
        } = settings;
        let g = finite("gain_m_per_v", gain_m_per_v)?;
        if g == 0.0 {
            return Err(ParamError::OutOfRange {
                field: "gain_m_per_v",
                value: g,
                requirement: "!= 0 (the stage's dy/du)",
            });
        }
        let ki = finite("ki_v_per_m_s", params.ki_v_per_m_s)?;
        if ki == 0.0 || (ki > 0.0) != (g > 0.0) {
            return Err(ParamError::OutOfRange {
                field: "ki_v_per_m_s",
                value: ki,
                requirement: "!= 0 and the sign of the stage's dy/du",
            });
        }
        let kp = finite("kp_v_per_m", params.kp_v_per_m)?;
        if kp != 0.0 && (kp > 0.0) != (ki > 0.0) {
            return Err(ParamError::OutOfRange {
                field: "kp_v_per_m",
                value: kp,
                requirement: "0 or the sign of ki_v_per_m_s",
            });
        }
        let proportional = libm::fabsf(kp * g);
        if proportional > MAX_PROPORTIONAL_LOOP_GAIN {
            return Err(ParamError::Implausible {
                field: "kp_v_per_m",
                value: kp,
                measure: "the proportional loop gain |kp·g|",
                ratio: proportional,
                limit: MAX_PROPORTIONAL_LOOP_GAIN,
            });
        }
        let integral = libm::fabsf(ki * g) * t;
        if integral > MAX_INTEGRAL_GAIN_PER_TICK {
            return Err(ParamError::Implausible {
                field: "ki_v_per_m_s",
                value: ki,
                measure: "the integral gain per tick |ki·g|·T",
                ratio: integral,
                limit: MAX_INTEGRAL_GAIN_PER_TICK,
            });
        }
        let lp = filter_frequency("lowpass_frequency_hz", params.lowpass_frequency_hz, t)?;
        let lp_q = positive("lowpass_q", params.lowpass_q)?;
        let notch = filter_frequency("notch_frequency_hz", params.notch_frequency_hz, t)?;
        let notch_q = positive("notch_q", params.notch_q)?;
        let notch_pole =
            filter_frequency("notch_pole_frequency_hz", params.notch_pole_frequency_hz, t)?;
        if notch_pole != 0.0 && notch == 0.0 {
            return Err(ParamError::OutOfRange {
                field: "notch_pole_frequency_hz",
                value: notch_pole,
                requirement: "0 without a notch (notch_frequency_hz = 0)",
            });
        }
        let tau = positive("transfer_time_constant_s", params.transfer_time_constant_s)?;
        let pi: [f32; 5] = pid::Builder::<f64>::default()
            .kp(f64::from(kp))
            .ki(f64::from(ki))
            .build(&f64::from(t));
        let servo = Self {
            params,
            lowpass: rbj(lp, lp_q, t, false),
            notch: if notch_pole == 0.0 {
                rbj(notch, notch_q, t, true)
            } else {
                notch_with_lead(notch, notch_pole, notch_q, t)
            },
            pi,
            limits,
            slew_step_v: limits.slew_limit_v_per_s * t,
            transfer_decay: libm::exp(-f64::from(t) / f64::from(tau)) as f32,
            sample_period_s: t,
        };
        if servo.coefficients().iter().flatten().all(|c| c.is_finite()) {
            Ok(servo)
        } else {
            Err(ParamError::Discretisation { sample_period_s: t })
        }
    }

    /// The parameters it was built from.
    pub fn params(&self) -> ServoParams {
        self.params
    }

    /// Loop period \[s\].
    pub fn sample_period_s(&self) -> f32 {
        self.sample_period_s
    }

    /// Coefficients `[b0, b1, b2, a1, a2]` (idsp's sign of a1, a2) of the low-pass, the notch
    /// and the PI.
    pub fn coefficients(&self) -> [[f32; 5]; 3] {
        [self.lowpass, self.notch, self.pi]
    }

    /// The servo's transfer function C(e^{jωT}) from error \[m\] to correction \[V\] at `hz`, as
    /// (re, im) — low-pass, notch and PI, without the limits.
    pub fn response(&self, hz: f64) -> (f64, f64) {
        let w = 2.0 * core::f64::consts::PI * hz * f64::from(self.sample_period_s);
        let c = [self.lowpass, self.notch, self.pi]
            .iter()
            .fold(Complex::ONE, |acc, ba| acc.mul(biquad_response(ba, w)));
        (c.re, c.im)
    }

    /// Bounds of this tick's output after `last_v`: the window, and the slew limit around
    /// `last_v` (the window wins when `last_v` lies outside it).
    #[inline(always)]
    fn bounds(&self, last_v: f32) -> (f32, f32) {
        let (lo, hi) = (self.limits.output_min_v, self.limits.output_max_v);
        if !last_v.is_finite() {
            return (lo, hi);
        }
        (
            min(max(last_v - self.slew_step_v, lo), hi),
            max(min(last_v + self.slew_step_v, hi), lo),
        )
    }

    /// One tick: reference `reference_m` and measurement `measured_m` \[m\] of the same instant,
    /// the feedforward voltage `feedforward_v` \[V\] of this tick (ignored in feedback mode).
    /// Returns the voltage to apply. Inlined: the loop's tick calls it once per axis.
    #[inline(always)]
    pub fn step(
        &self,
        state: &mut ServoState,
        reference_m: f32,
        measured_m: f32,
        feedforward_v: f32,
    ) -> ServoOutput {
        let mode = state.mode;
        let ff = if mode.feedforward() {
            feedforward_v
        } else {
            0.0
        };
        let last = state.output_v;
        if !ff.is_finite() {
            return ServoOutput {
                voltage_v: last,
                correction_v: state.pi.y[0],
                status: ServoStatus::Held,
            };
        }
        let error = reference_m - measured_m;
        let filtered = if error.is_finite() {
            let e = state.lowpass.process(&self.lowpass, error);
            Some(state.notch.process(&self.notch, e))
        } else {
            None
        };
        let mut status = ServoStatus::Tracking;
        let wanted = if state.transfer {
            last - ff
        } else if mode.feedback() {
            match filtered {
                Some(e) => {
                    let mut pi = state.pi;
                    pi.process(&self.pi, e)
                }
                None => {
                    status = ServoStatus::Held;
                    state.pi.y[0]
                }
            }
        } else {
            state.pi.y[0] * self.transfer_decay
        };
        let (lo, hi) = self.bounds(last);
        let sum = ff + wanted;
        let u = if sum.is_finite() {
            clamp(sum, lo, hi)
        } else {
            clamp(last, lo, hi)
        };
        if u != sum && status == ServoStatus::Tracking {
            status = ServoStatus::Limited;
        }
        let correction = u - ff;
        if let Some(e) = filtered {
            state.pi.x = [e, state.pi.x[0]];
        }
        if filtered.is_some() || !mode.feedback() {
            state.pi.y = [correction, state.pi.y[0]];
            state.transfer = false;
        }
        state.output_v = u;
        ServoOutput {
            voltage_v: u,
            correction_v: correction,
            status,
        }
    }
}

/// A complex number for the frequency responses of the tuning (f64, host-side arithmetic).
#[derive(Debug, Clone, Copy, PartialEq)]
struct Complex {
    re: f64,
    im: f64,
}

impl Complex {
    const ONE: Self = Self { re: 1.0, im: 0.0 };

    fn polar(r: f64, phase: f64) -> Self {
        Self {
            re: r * libm::cos(phase),
            im: r * libm::sin(phase),
        }
    }
    fn add(self, o: Self) -> Self {
        Self {
            re: self.re + o.re,
            im: self.im + o.im,
        }
    }
    fn mul(self, o: Self) -> Self {
        Self {
            re: self.re * o.re - self.im * o.im,
            im: self.re * o.im + self.im * o.re,
        }
    }
    fn div(self, o: Self) -> Self {
        let d = o.re * o.re + o.im * o.im;
        Self {
            re: (self.re * o.re + self.im * o.im) / d,
            im: (self.im * o.re - self.re * o.im) / d,
        }
    }
    fn abs(self) -> f64 {
        libm::hypot(self.re, self.im)
    }
    fn arg(self) -> f64 {
        libm::atan2(self.im, self.re)
    }
}

/// H(e^{jw}) of `y0 = b0·x0 + b1·x1 + b2·x2 + a1·y1 + a2·y2`, `w = ωT`.
fn biquad_response(ba: &[f32; 5], w: f64) -> Complex {
    let z1 = Complex::polar(1.0, -w);
    let z2 = Complex::polar(1.0, -2.0 * w);
    let b = |i: usize| f64::from(ba[i]);
    let num = Complex { re: b(0), im: 0.0 }
        .add(z1.mul(Complex { re: b(1), im: 0.0 }))
        .add(z2.mul(Complex { re: b(2), im: 0.0 }));
    let den = Complex::ONE
        .add(z1.mul(Complex { re: -b(3), im: 0.0 }))
        .add(z2.mul(Complex { re: -b(4), im: 0.0 }));
    num.div(den)
}

/// What the tuning rule needs to know about one axis.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct StageDynamics {
    /// g: the small-signal gain dy/du of largest magnitude over the reachable states \[m/V\]
    /// (its sign is the stage's; [`StageDynamics::from_model`]).
    pub gain_m_per_v: f32,
    /// f_n: the first mechanical mode \[Hz\].
    pub mode_frequency_hz: f32,
    /// ζ: its damping ratio.
    pub mode_damping: f32,
    /// τ: sensor-to-actuator latency \[s\]: conversion, computation and the hold's half period.
    pub latency_s: f32,
}

impl StageDynamics {
    /// The dynamics of an identified static model (g: the slope of largest magnitude of
    /// [`StaticModel::slope_range`]) with its first mode and the loop's latency.
    pub fn from_model(
        model: &StaticModel,
        mode_frequency_hz: f32,
        mode_damping: f32,
        latency_s: f32,
    ) -> Self {
        Self::from_slope_range(
            model.slope_range(),
            mode_frequency_hz,
            mode_damping,
            latency_s,
        )
    }

    /// The dynamics of the model a compensator inverts, its gain g taken over the states and
    /// one-step moves the compensator's slew limit allows: the slope of largest magnitude of
    /// [`StaticModel::slope_range_for_step`] at the step `slew_limit_v_per_s · sample_period_s`
    /// (for a model without a rate-dependent gain that is [`StaticModel::slope_range`], as
    /// [`StageDynamics::from_model`]; with one, every step of the whole window would count moves
    /// the compensator never makes, whose slopes it does not invert).
    pub fn from_compensator(
        compensator: &crate::compensator::Compensator,
        mode_frequency_hz: f32,
        mode_damping: f32,
        latency_s: f32,
    ) -> Self {
        let model = compensator.model();
        let settings = compensator.settings();
        let step = settings.limits.slew_limit_v_per_s * settings.sample_period_s;
        Self::from_slope_range(
            model.slope_range_for_step(step),
            mode_frequency_hz,
            mode_damping,
            latency_s,
        )
    }

    /// g: the slope of largest magnitude of the one-step slopes `(lo, hi)` \[m/V\].
    fn from_slope_range(
        (lo, hi): (f32, f32),
        mode_frequency_hz: f32,
        mode_damping: f32,
        latency_s: f32,
    ) -> Self {
        Self {
            gain_m_per_v: if libm::fabsf(lo) > libm::fabsf(hi) {
                lo
            } else {
                hi
            },
            mode_frequency_hz,
            mode_damping,
            latency_s,
        }
    }

    /// P(jω) = g·ω_n² / (ω_n² − ω² + 2jζω_nω) · e^{−jωτ}, with the mode at `mode_scale`·f_n.
    fn plant(&self, hz: f64, mode_scale: f64) -> Complex {
        let w = 2.0 * core::f64::consts::PI * hz;
        let wn = 2.0 * core::f64::consts::PI * f64::from(self.mode_frequency_hz) * mode_scale;
        let mode = Complex {
            re: wn * wn,
            im: 0.0,
        }
        .div(Complex {
            re: wn * wn - w * w,
            im: 2.0 * f64::from(self.mode_damping) * wn * w,
        });
        Complex::polar(f64::from(self.gain_m_per_v), -w * f64::from(self.latency_s)).mul(mode)
    }
}

/// The design goal of [`tune`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TuningGoal {
    /// φ_m: phase margin at the crossover \[°\].
    pub phase_margin_deg: f32,
    /// M_s: largest |1/(1 + L)| allowed at any frequency (2: gain margin ≥ 6 dB).
    pub sensitivity_peak: f32,
    /// Relative error of f_n the loop must survive: the margins hold with the mode at
    /// (1 ± this)·f_n as well.
    pub mode_uncertainty: f32,
    /// f_z / f_c: the PI's zero above the crossover (+∞: pure integral action, the default:
    /// below its mode the stage is a static gain, so an integrator alone falls at −20 dB per
    /// decade through the crossover, while a proportional part would hold the loop gain flat up
    /// to the mode, where latency and the mode's peak then cost the margins).
    pub zero_ratio: f32,
    /// f_lp / f_n: the low-pass corner relative to the mode, unless the latency puts it higher
    /// (at least 1/(4τ), see [`tune`]).
    pub lowpass_ratio: f32,
    /// Q of the notch near f_n: the narrowest notch [`tune`] tries (then 0.7, 0.5 and 0.35 times it).
    pub notch_q: f32,
    /// τ of the bumpless hand-over without feedback \[s\].
    pub transfer_time_constant_s: f32,
    /// Also try notches with lead, which hold the mode by phase ([`tune`]): a higher crossover
    /// on a fast loop, but a loop that needs the mode where `StageDynamics` puts it. Off by
    /// default: on an XY-like stage at 50 kHz the loop so tuned is unstable with the mode 20 %
    /// below f_n or without it, where the plain notch's is stable
    /// (`a_notch_with_lead_holds_the_mode_in_time`).
    pub mode_by_phase: bool,
}

impl Default for TuningGoal {
    /// φ_m = 60°, M_s = 1.6, f_n ± 10 %, pure integral action, the low-pass search starting at
    /// f_n (Butterworth; or 1/(4τ) when higher), notch Q = 1 (or 0.7, 0.5, 0.35), hand-over
    /// τ = 20 ms, plain notches only.
    fn default() -> Self {
        Self {
            phase_margin_deg: 60.0,
            sensitivity_peak: 1.6,
            mode_uncertainty: 0.1,
            zero_ratio: f32::INFINITY,
            lowpass_ratio: 1.0,
            notch_q: 1.0,
            transfer_time_constant_s: 0.02,
            mode_by_phase: false,
        }
    }
}

/// The result of [`tune`]: the parameters and the margins the rule found for them.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Tuning {
    /// The servo parameters (the stage file's `[x.servo]`).
    pub params: ServoParams,
    /// f_c: the loop's crossover \[Hz\] (nominal plant).
    pub crossover_hz: f32,
    /// Phase margin at f_c \[°\] (nominal plant).
    pub phase_margin_deg: f32,
    /// Largest |1/(1 + L)| over the frequency grid and the mode's range.
    pub sensitivity_peak: f32,
    /// −3 dB bandwidth of the feedback loop alone, |L/(1 + L)| \[Hz\] (nominal plant).
    pub closed_loop_bandwidth_hz: f32,
}

/// Points of the log frequency grid per decade (at least; see [`GRID_PER_DAMPING`]).
const GRID_PER_DECADE: f64 = 120.0;

/// Points per decade times the mode's ζ: a mode's phase turns by up to 1/ζ rad per unit of
/// ln f, so 3/ζ points per decade keep each step of the grid below 0.77 rad (44°) and the
/// unwrapped phases of [`margins`] true.
const GRID_PER_DAMPING: f64 = 3.0;

/// Unwraps an angle along a grid: the step from `last` to `arg` taken in (−π, π].
fn unwrap_step(arg: f64, last: f64) -> f64 {
    let mut step = arg - last;
    if step > core::f64::consts::PI {
        step -= 2.0 * core::f64::consts::PI;
    } else if step <= -core::f64::consts::PI {
        step += 2.0 * core::f64::consts::PI;
    }
    step
}

/// Margins of one candidate over the grid: (phase margin at the nominal crossover,
/// crossover, sensitivity peak, closed-loop −3 dB bandwidth); `None` when, for any of the
/// mode's `scales`, the closed loop is unstable, |L| never falls below 1, or |L| ≥ 1 at the
/// Nyquist frequency. The crossover is the first frequency where |L| falls below 1; its phase is
/// unwrapped along the grid from `low_hz` (where the integrator holds it near −90°), so a loop
/// whose phase has turned past −180° before it crosses is not read as a large margin.
///
/// Stability is the Nyquist criterion for an open loop that is stable but for the
/// integrator: along ω from 0⁺ to ∞ the angle of 1 + L must rise by exactly +90° (from −90°,
/// where the integrator's |L| is large, to 0°, where L has vanished), i.e. 1 + L does not
/// encircle the origin. With |L| < 1 at the Nyquist frequency the angle there lies within ±90°,
/// so the unwrapped angle of 1 + L must end within ±90°. This also admits a loop that crosses
/// 0 dB three times, around a mode it holds by phase (|L| > 1 at the mode, its phase far from
/// −180°), which a single-crossing rule would refuse.
fn margins(
    servo: &Servo,
    dynamics: &StageDynamics,
    scales: &[f64],
    low_hz: f64,
    nyquist_hz: f64,
) -> Option<(f64, f64, f64, f64)> {
    let per_decade = GRID_PER_DECADE.max(GRID_PER_DAMPING / f64::from(dynamics.mode_damping));
    let points = (libm::log10(nyquist_hz / low_hz) * per_decade) as usize;
    let mut peak: f64 = 0.0;
    let mut nominal = None;
    let mut nominal_bandwidth = nyquist_hz;
    for (i, &scale) in scales.iter().enumerate() {
        let mut crossed = false;
        let mut bandwidth = nyquist_hz;
        let (mut phase, mut last_arg) = (0.0, 0.0);
        let (mut winding, mut last_winding_arg) = (0.0, 0.0);
        let mut last_abs = f64::INFINITY;
        for k in 0..=points {
            let f = low_hz * libm::pow(10.0, k as f64 / per_decade);
            let (re, im) = servo.response(f.min(nyquist_hz * 0.999));
            let l = dynamics.plant(f, scale).mul(Complex { re, im });
            let arg = l.arg();
            let one_plus = Complex::ONE.add(l);
            let winding_arg = one_plus.arg();
            if k == 0 {
                phase = arg;
                winding = winding_arg;
            } else {
                phase += unwrap_step(arg, last_arg);
                winding += unwrap_step(winding_arg, last_winding_arg);
            }
            last_arg = arg;
            last_winding_arg = winding_arg;
            peak = peak.max(1.0 / one_plus.abs());
            let t = l.div(one_plus).abs();
            if bandwidth == nyquist_hz && t < core::f64::consts::FRAC_1_SQRT_2 && k > 0 {
                bandwidth = f;
            }
            last_abs = l.abs();
            if !crossed && last_abs < 1.0 {
                crossed = true;
                let margin = 180.0 + phase.to_degrees();
                if margin <= 0.0 {
                    return None;
                }
                if i == 0 {
                    nominal = Some((margin, f));
                }
            }
        }
        if !crossed || last_abs >= 1.0 || libm::fabs(winding) >= core::f64::consts::FRAC_PI_2 {
            return None;
        }
        if i == 0 {
            nominal_bandwidth = bandwidth;
        }
    }
    nominal.map(|(pm, fc)| (pm, fc, peak, nominal_bandwidth))
}

/// The notch's Q relative to the goal's, in the order [`tune`] tries them: the goal's, then
/// wider notches (a lower Q attenuates more over the mode's uncertainty, for more phase lag
/// at the crossover).
const NOTCH_WIDENING: [f32; 4] = [1.0, 0.7, 0.5, 0.35];

/// The notch's centre relative to f_n, in the order [`tune`] tries them: at the mode, then
/// below and above it (a notch below f_n takes its phase lag further from the crossover's
/// side of the mode into the region where the mode's own rise needs attenuation; above, it
/// lags less at the crossover).
const NOTCH_PLACEMENT: [f64; 5] = [1.0, 0.9, 1.1, 0.8, 1.25];

/// The low-pass corner relative to the rule's f_lp (module doc of [`tune`]), in the order tried.
const LOWPASS_PLACEMENT: [f64; 6] = [1.0, 0.7, 1.4, 2.0, 3.0, 5.0];

/// The poles of a notch with lead relative to its centre, in the order [`tune`] tries them
/// after the plain notches (1): the further up, the more lead above the mode and the more gain
/// at high frequency, (f_p/f_notch)².
const LEAD_POLE_PLACEMENT: [f64; 3] = [2.0, 4.0, 8.0];

/// The Q of a notch with lead's poles relative to the goal's notch Q, in the order tried (a
/// higher Q turns the phase faster near f_p).
const LEAD_POLE_Q: [f32; 3] = [1.0, 2.0, 2.8];

/// The crossover scan of [`tune`] for one filter shape: everything but the gains fixed.
struct Scan<'a> {
    dynamics: &'a StageDynamics,
    limits: CompensatorSettings,
    /// sgn g: the gains take the stage's sign.
    sign: f64,
    /// The stage's gain g \[m/V\] (the loop-gain bounds of [`Servo::new`]).
    gain_m_per_v: f32,
    zero_ratio: f32,
    /// The mode at f_n and at (1 ∓ δ)·f_n.
    scales: [f64; 3],
    nyquist_hz: f64,
    mode_hz: f64,
    pm_goal: f64,
    ms_goal: f64,
}

impl Scan<'_> {
    /// The highest crossover f_c ≤ f_n/2 (steps of 2 % down to f_n/10⁴, and not below
    /// `floor_hz`, a crossover another shape already reaches) whose servo of filter shape `unit`
    /// (its ki and kp replaced) meets the goal; `None` when none does.
    fn highest(&self, unit: ServoParams, floor_hz: f64) -> Result<Option<Tuning>, ParamError> {
        let mut fc = self.mode_hz.min(self.nyquist_hz) / 2.0;
        let floor_hz = floor_hz.max(self.mode_hz * 1e-4);
        while fc > floor_hz {
            // ki = 1, kp = 1/(2π f_z): |L(f_c)| for unit ki, then scale.
            let wz = 2.0 * core::f64::consts::PI * fc * f64::from(self.zero_ratio);
            let with = |ki: f64| {
                let mut p = unit;
                p.ki_v_per_m_s = (ki * self.sign) as f32;
                p.kp_v_per_m = (ki * self.sign / wz) as f32;
                Servo::new(p, self.limits, self.gain_m_per_v)
            };
            let probe = with(1.0)?;
            let (re, im) = probe.response(fc);
            let l1 = self.dynamics.plant(fc, 1.0).mul(Complex { re, im }).abs();
            // A shape that needs more gain than the servo accepts cannot cross here.
            let Ok(servo) = with(1.0 / l1) else {
                fc /= 1.02;
                continue;
            };
            // The unwrapped phase is the wrapped one less whole turns (these filters lead by
            // less than a turn), so a wrapped margin below the goal needs no grid.
            let (re, im) = servo.response(fc);
            let wrapped = 180.0
                + self
                    .dynamics
                    .plant(fc, 1.0)
                    .mul(Complex { re, im })
                    .arg()
                    .to_degrees();
            if wrapped < self.pm_goal {
                fc /= 1.02;
                continue;
            }
            if let Some((pm, crossover, peak, bandwidth)) = margins(
                &servo,
                self.dynamics,
                &self.scales,
                fc / 100.0,
                self.nyquist_hz,
            ) {
                if pm >= self.pm_goal && peak <= self.ms_goal {
                    return Ok(Some(Tuning {
                        params: servo.params(),
                        crossover_hz: crossover as f32,
                        phase_margin_deg: pm as f32,
                        sensitivity_peak: peak as f32,
                        closed_loop_bandwidth_hz: bandwidth as f32,
                    }));
                }
            }
            fc /= 1.02;
        }
        Ok(None)
    }
}

/// Servo parameters from the stage's dynamics, by loop shaping against the nominal plant
/// `P(s) = g·ω_n²/(s² + 2ζω_n s + ω_n²)·e^{−sτ}` and the discrete controller itself.
///
/// The rule: the mode is held by a notch near f_n — a plain notch (gain stabilisation), or, with
/// `goal.mode_by_phase`, also a notch with lead (module doc) whose poles lie above it, which
/// holds the mode by phase instead — a Butterworth low-pass rolls the loop off, PI zero at
/// f_z = `zero_ratio`·f_c, and ki is scaled so that |L(f_c)| = 1. The filters' placement is searched around a start set by
/// the loop's latency τ (which falls with the loop period):
/// ```text
/// f_lp0 = max(lowpass_ratio·f_n, 1/(4τ))                    the low-pass corner's start
/// f_lp = min(c·f_lp0, 0.45·f_s),       c ∈ {1, 0.7, 1.4, 2, 3, 5}
/// f_notch = min(p·f_n, 0.45·f_s),      p ∈ {1, 0.9, 1.1, 0.8, 1.25}
/// plain notch:  Q_notch = w·notch_q,   w ∈ {1, 0.7, 0.5, 0.35}
/// with lead:    f_p = min(m·f_notch, 0.45·f_s), m ∈ {2, 4, 8};  Q = w·notch_q, w ∈ {1, 2, 2.8}
/// ```
/// Below 1/(4τ) the delay alone turns the loop by less than 90° (e^{−jωτ}, ωτ < π/2), so a
/// low-pass corner there would spend at the crossover phase that the delay leaves free. A notch
/// of lower Q attenuates more over f_n·(1 ± δ) and costs more phase at f_c; one above f_n lags
/// less at f_c, one below attenuates more of the mode's quasi-static rise. Every combination is
/// scanned and the highest crossover wins (a tie keeps the combination tried first, in the
/// order listed, the plain notches before those with lead). For each shape, f_c is the
/// highest crossover, scanned downwards from f_n/2 in steps of 2 %, for which
/// 1. the phase margin at f_c (the first frequency where |L| falls below 1) is at least φ_m,
///    the phase unwrapped from low frequencies (a loop whose phase passes −180° below its
///    crossover encircles −1 and is refused);
/// 2. the closed loop is stable by the Nyquist criterion (the angle of 1 + L rises
///    by exactly 90° from 0⁺ to Nyquist), and |L| < 1 at Nyquist;
/// 3. |1/(1 + L)| ≤ M_s at every frequency up to Nyquist;
///
/// with 2 and 3, and a positive unwrapped phase margin, also for the mode at
/// (1 ± `mode_uncertainty`)·f_n. Where a notch with lead holds the mode by phase, |L| rises
/// above 1 again around f_n; condition 3 keeps each of those further crossings at least
/// 2·asin(1/(2M_s)) (36° for M_s = 1.6) from −180°. The gain g should be the
/// largest |dy/du| of the model: a lower local gain lowers the crossover, which only adds phase.
/// With a plain notch, what caps f_c on a lightly damped mode is condition 3 between f_c and
/// f_n, where the mode's quasi-static rise 1/(1 − (f/f_n)²) and the filters' lag bring L
/// towards −1 (on the XY stage, ζ = 0.03, the peak of |1/(1 + L)| sits near f_n/2, and f_c stays
/// near f_n/5 at every rate). A notch with lead needs a loop whose latency leaves the phase at
/// the mode free (τ·f_n well below 1/4): on the XY stage at 50 kHz (τ = 35 µs) it is chosen and
/// f_c rises to about f_n/2.5; at 10 and 20 kHz the plain notch still wins. It also needs the
/// mode itself: its gain above f_n rises by (f_p/f_notch)², which only the mode's roll-off keeps
/// below 1, so a stage whose mode lies well below the stated f_n (a payload) or that has none
/// is unstable under it; hence it is tried only when the goal asks.
/// Refused (`OutOfRange` on `phase_margin_deg`) when no crossover above f_n/10⁴ meets the goal.
pub fn tune(
    dynamics: &StageDynamics,
    goal: &TuningGoal,
    limits: CompensatorSettings,
) -> Result<Tuning, ParamError> {
    let t = positive("sample_period_s", limits.sample_period_s)?;
    let g = finite("gain_m_per_v", dynamics.gain_m_per_v)?;
    if g == 0.0 {
        return Err(ParamError::OutOfRange {
            field: "gain_m_per_v",
            value: g,
            requirement: "!= 0",
        });
    }
    let fs = 1.0 / f64::from(t);
    let fn_hz = f64::from(positive("mode_frequency_hz", dynamics.mode_frequency_hz)?);
    positive("mode_damping", dynamics.mode_damping)?;
    let tau = finite("latency_s", dynamics.latency_s)?;
    if tau < 0.0 {
        return Err(ParamError::OutOfRange {
            field: "latency_s",
            value: tau,
            requirement: ">= 0",
        });
    }
    let pm_goal = f64::from(finite("phase_margin_deg", goal.phase_margin_deg)?);
    let ms_goal = f64::from(positive("sensitivity_peak", goal.sensitivity_peak)?);
    let du = f64::from(finite("mode_uncertainty", goal.mode_uncertainty)?).clamp(0.0, 0.9);
    let zero_ratio = positive("zero_ratio", goal.zero_ratio).or_else(|e| {
        if goal.zero_ratio == f32::INFINITY {
            Ok(f32::INFINITY)
        } else {
            Err(e)
        }
    })?;
    let cap = MAX_FILTER_FRACTION as f64 * 0.999 * fs;
    let ratio = f64::from(positive("lowpass_ratio", goal.lowpass_ratio)?);
    // Where the latency alone has turned the loop's phase by 90°: the low-pass goes no lower.
    let quarter_turn_hz = if tau > 0.0 {
        0.25 / f64::from(tau)
    } else {
        f64::INFINITY
    };
    let lp = (ratio * fn_hz).max(quarter_turn_hz).min(cap);
    let notch = fn_hz.min(cap);
    let notch_q = positive("notch_q", goal.notch_q)?;
    let scan = Scan {
        dynamics,
        limits,
        sign: if g > 0.0 { 1.0 } else { -1.0 },
        gain_m_per_v: g,
        zero_ratio,
        scales: [1.0, 1.0 - du, 1.0 + du],
        nyquist_hz: 0.5 * fs,
        mode_hz: fn_hz,
        pm_goal,
        ms_goal,
    };
    // The notch shapes in the order tried: (pole / centre, Q relative to the goal's): the
    // plain notches first, then the notches with lead.
    let plain = NOTCH_WIDENING.map(|w| (1.0, w));
    let lead_poles: &[f64] = if goal.mode_by_phase {
        &LEAD_POLE_PLACEMENT
    } else {
        &[]
    };
    let lead = lead_poles
        .iter()
        .flat_map(|&p| LEAD_POLE_Q.iter().map(move |&q| (p, q)));
    let mut best: Option<Tuning> = None;
    for placement in NOTCH_PLACEMENT {
        let centre = (notch * placement).min(cap);
        for (pole_ratio, q_ratio) in plain.iter().copied().chain(lead.clone()) {
            let pole = (centre * pole_ratio).min(cap);
            // A lead whose poles the cap puts at the centre, or where a lower ratio put them
            // already, is a shape scanned before.
            let scanned = LEAD_POLE_PLACEMENT
                .iter()
                .any(|&r| r < pole_ratio && (centre * r).min(cap) == pole);
            if pole_ratio > 1.0 && (pole <= centre || scanned) {
                continue;
            }
            for corner in LOWPASS_PLACEMENT {
                let shape = ServoParams {
                    kp_v_per_m: 0.0,
                    ki_v_per_m_s: 1.0,
                    lowpass_frequency_hz: (lp * corner).min(cap) as f32,
                    lowpass_q: core::f32::consts::FRAC_1_SQRT_2,
                    notch_frequency_hz: centre as f32,
                    notch_q: notch_q * q_ratio,
                    notch_pole_frequency_hz: if pole_ratio > 1.0 { pole as f32 } else { 0.0 },
                    transfer_time_constant_s: goal.transfer_time_constant_s,
                };
                // Only a strictly higher crossover replaces the best: a tie keeps the shape
                // tried first (the notch at f_n, the narrower notch, the plain notch, the
                // rule's corner).
                let floor = best.map_or(0.0, |b| f64::from(b.crossover_hz));
                if let Some(t) = scan.highest(shape, floor)? {
                    if best.is_none_or(|b| t.crossover_hz > b.crossover_hz) {
                        best = Some(t);
                    }
                }
            }
        }
    }
    if let Some(t) = best {
        return Ok(t);
    }
    Err(ParamError::OutOfRange {
        field: "phase_margin_deg",
        value: goal.phase_margin_deg,
        requirement: "reachable: no crossover above f_n / 1e4 meets the margins",
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    const T: f32 = 1e-4;
    /// The stage's gain dy/du \[m/V\] (40 µm over 120 V).
    const G: f32 = 3.3e-7;

    fn limits() -> CompensatorSettings {
        CompensatorSettings {
            limits: Limits::new(0.0, 120.0, 1e5),
            sample_period_s: T,
        }
    }

    fn params() -> ServoParams {
        ServoParams {
            kp_v_per_m: 2e5,
            ki_v_per_m_s: 1e9,
            lowpass_frequency_hz: 2000.0,
            lowpass_q: core::f32::consts::FRAC_1_SQRT_2,
            notch_frequency_hz: 2200.0,
            notch_q: 1.0,
            notch_pole_frequency_hz: 0.0,
            transfer_time_constant_s: 0.01,
        }
    }

    fn isclose(a: f64, b: f64, rtol: f64, atol: f64) -> bool {
        (a - b).abs() <= atol + rtol * b.abs()
    }

    #[test]
    fn refuses_what_it_cannot_run() {
        let refused_on = |p: ServoParams, g: f32| match Servo::new(p, limits(), g) {
            Err(ParamError::OutOfRange { field, .. }) | Err(ParamError::NonFinite { field }) => {
                field
            }
            other => panic!("accepted or wrong error: {other:?}"),
        };
        let refused = |p: ServoParams| refused_on(p, G);
        let mut p = params();
        p.ki_v_per_m_s = 0.0;
        assert_eq!(refused(p), "ki_v_per_m_s");
        let mut p = params();
        p.kp_v_per_m = -1.0;
        assert_eq!(refused(p), "kp_v_per_m");
        let mut p = params();
        p.notch_frequency_hz = 4600.0;
        assert_eq!(refused(p), "notch_frequency_hz");
        let mut p = params();
        p.lowpass_q = 0.0;
        assert_eq!(refused(p), "lowpass_q");
        let mut p = params();
        p.transfer_time_constant_s = f32::NAN;
        assert_eq!(refused(p), "transfer_time_constant_s");
        let mut l = limits();
        l.limits.output_max_v = -1.0;
        assert!(Servo::new(params(), l, G).is_err());
        // Negative gains for a stage with dy/du < 0.
        let mut p = params();
        p.kp_v_per_m = -2e5;
        p.ki_v_per_m_s = -1e9;
        assert!(Servo::new(p, limits(), -G).is_ok());
        // ... and refused on a stage with dy/du > 0 (positive feedback).
        assert_eq!(refused_on(p, G), "ki_v_per_m_s");
    }

    /// Loop gains beyond the documented bounds are refused as implausible, with the measure; the
    /// bounds themselves are accepted.
    #[test]
    fn loop_gains_are_bounded() {
        let implausible = |p: ServoParams| match Servo::new(p, limits(), G) {
            Err(ParamError::Implausible {
                field,
                ratio,
                limit,
                ..
            }) => (field, ratio, limit),
            other => panic!("accepted or wrong error: {other:?}"),
        };
        let mut p = params();
        p.kp_v_per_m = 1e38;
        let (field, ratio, limit) = implausible(p);
        assert_eq!(field, "kp_v_per_m");
        assert!(ratio > 1e30 && limit == MAX_PROPORTIONAL_LOOP_GAIN);
        p.kp_v_per_m = 1.01 * MAX_PROPORTIONAL_LOOP_GAIN / G;
        assert_eq!(implausible(p).0, "kp_v_per_m");
        p.kp_v_per_m = 0.99 * MAX_PROPORTIONAL_LOOP_GAIN / G;
        assert!(Servo::new(p, limits(), G).is_ok());
        let mut p = params();
        p.ki_v_per_m_s = 1.01 * MAX_INTEGRAL_GAIN_PER_TICK / (G * T);
        assert_eq!(implausible(p).0, "ki_v_per_m_s");
        p.ki_v_per_m_s = 0.99 * MAX_INTEGRAL_GAIN_PER_TICK / (G * T);
        assert!(Servo::new(p, limits(), G).is_ok());
        // The slew rule is the compensator's.
        let mut l = limits();
        l.limits.slew_limit_v_per_s = 1e38;
        assert!(matches!(
            Servo::new(params(), l, G),
            Err(ParamError::Implausible {
                field: "slew_limit_v_per_s",
                ..
            })
        ));
    }

    #[test]
    fn filters_and_pi_are_what_the_doc_says() {
        let s = Servo::new(params(), limits(), G).unwrap();
        let [lp, notch, pi] = s.coefficients();
        let w = |hz: f64| 2.0 * core::f64::consts::PI * hz * f64::from(T);
        assert!(isclose(biquad_response(&lp, 0.0).abs(), 1.0, 1e-5, 0.0));
        assert!(isclose(
            biquad_response(&lp, w(2000.0)).abs(),
            0.5f64.sqrt(),
            1e-4,
            0.0
        ));
        assert!(biquad_response(&notch, w(2200.0)).abs() < 1e-5);
        assert!(isclose(biquad_response(&notch, 0.0).abs(), 1.0, 1e-5, 0.0));
        let (kp, kit) = (2e5, 1e9 * f64::from(T));
        assert!(isclose(f64::from(pi[0]), kp + kit, 1e-6, 0.0));
        assert!(isclose(f64::from(pi[1]), -kp, 1e-6, 0.0));
        assert_eq!([pi[2], pi[3], pi[4]], [0.0, 1.0, 0.0]);
    }

    /// A static stage g·u with one tick of delay and a slow creep-like drift of its output;
    /// the largest |error| over the second half.
    fn closed_loop(mode: ServoMode, ff_gain_error: f32, ticks: usize) -> (f32, ServoState) {
        let servo = Servo::new(params(), limits(), G).unwrap();
        let g = 0.5e-6;
        let mut state = ServoState::at_rest(0.0, mode);
        let (mut y, mut err) = (0.0f32, 0.0f32);
        for k in 0..ticks {
            if k == ticks / 2 {
                err = 0.0;
            }
            let r = 30e-6 + 10e-6 * libm::sinf(k as f32 * 0.002);
            let drift = 1e-6 * (1.0 - libm::expf(-(k as f32) * T / 0.05));
            let ff = r / (g * (1.0 + ff_gain_error));
            let u = servo.step(&mut state, r, y, ff).voltage_v;
            y = g * u + drift;
            err = err.max((r - y).abs());
        }
        (err, state)
    }

    #[test]
    fn feedback_removes_what_the_feedforward_misses() {
        let (ff_only, _) = closed_loop(ServoMode::Feedforward, -0.05, 20_000);
        let (hybrid, _) = closed_loop(ServoMode::FeedforwardFeedback, -0.05, 20_000);
        let (fb, _) = closed_loop(ServoMode::Feedback, -0.05, 20_000);
        assert!(ff_only > 1e-6, "{ff_only}");
        assert!(hybrid < 0.05 * ff_only, "{hybrid} vs {ff_only}");
        assert!(fb < 0.2 * ff_only, "{fb} vs {ff_only}");
        assert!(hybrid < 0.2 * fb, "{hybrid} vs {fb}");
    }

    #[test]
    fn anti_windup_leaves_the_limit_at_once() {
        let servo = Servo::new(params(), limits(), G).unwrap();
        let mut state = ServoState::at_rest(100.0, ServoMode::FeedforwardFeedback);
        // The stage does not move: the error stays, the sum sits at the window's top.
        for _ in 0..5000 {
            let out = servo.step(&mut state, 80e-6, 0.0, 110.0);
            assert!(out.voltage_v <= 120.0);
        }
        assert_eq!(state.output_v(), 120.0);
        assert_eq!(state.correction_v(), 10.0);
        // The error reverses: the output comes off the limit within a few ticks.
        let mut left = None;
        for k in 0..20 {
            let out = servo.step(&mut state, 0.0, 1e-6, 110.0);
            if out.voltage_v < 120.0 {
                left = Some(k);
                break;
            }
        }
        assert!(left.is_some_and(|k| k < 5), "{left:?}");
    }

    #[test]
    fn mode_changes_are_bumpless() {
        let servo = Servo::new(params(), limits(), G).unwrap();
        let g = 0.5e-6;
        let mut state = ServoState::at_rest(30e-6 / g, ServoMode::FeedforwardFeedback);
        let mut y = 30e-6f32;
        let mut last = state.output_v();
        let modes = [
            ServoMode::Feedback,
            ServoMode::Feedforward,
            ServoMode::FeedforwardFeedback,
            ServoMode::OpenLoop,
            ServoMode::Feedback,
        ];
        for k in 0..25_000usize {
            if k % 5000 == 4999 {
                state.set_mode(modes[k / 5000]);
            }
            let r = 30e-6 + 10e-6 * libm::sinf(k as f32 * 0.001);
            // A feedforward 10 % off, so every mode has something different to hand over.
            let ff = r / (g * 1.1) + 2.0;
            let u = servo.step(&mut state, r, y, ff).voltage_v;
            // The reference moves ≤ 0.02 V per tick and the integrator ≤ ki·T·|e| ≈ 0.2 V with
            // the few µm a mode without feedback leaves; a bump would be the 3–4 V between modes.
            if k > 0 {
                assert!((u - last).abs() < 0.5, "tick {k}: {last} -> {u}");
            }
            last = u;
            y = g * u + 1e-7;
        }
    }

    #[test]
    fn a_feedforward_that_takes_over_the_correction_leaves_the_sum_unchanged() {
        // The same run twice with feedback: once with the feedforward as it is, once with a
        // feedforward that steps up by Δ at tick 3000 (a new learned table) and the servo told
        // so. The sums agree to rounding; without `take_over` the sum jumps by Δ at once.
        let servo = Servo::new(params(), limits(), G).unwrap();
        let g = 0.5e-6;
        let delta = 3.0f32;
        let run = |told: bool, stepped: bool| {
            let mut state = ServoState::at_rest(60.0, ServoMode::FeedforwardFeedback);
            let mut y = 30e-6f32;
            let mut out = [0.0f32; 4000];
            for (k, u) in out.iter_mut().enumerate() {
                let r = 30e-6 + 10e-6 * libm::sinf(k as f32 * 0.001);
                let mut ff = r / (g * 1.1) + 2.0;
                if stepped && k >= 3000 {
                    ff += delta;
                }
                if told && k == 3000 {
                    state.take_over(delta);
                }
                *u = servo.step(&mut state, r, y, ff).voltage_v;
                y = g * *u + 1e-7;
            }
            out
        };
        let (plain, handed) = (run(false, false), run(true, true));
        for k in 0..4000 {
            assert!((plain[k] - handed[k]).abs() < 1e-3, "tick {k}");
        }
        let jumped = run(false, true);
        assert!((jumped[3000] - plain[3000] - delta).abs() < 0.1);
        // Without feedback the feedforward passes through: nothing to take over.
        let mut state = ServoState::at_rest(60.0, ServoMode::Feedforward);
        servo.step(&mut state, 30e-6, 30e-6, 60.0);
        let before = state;
        state.take_over(delta);
        assert_eq!(state, before);
    }

    #[test]
    fn never_leaves_the_window_or_the_slew_limit() {
        let servo = Servo::new(params(), limits(), G).unwrap();
        let mut state = ServoState::at_rest(60.0, ServoMode::FeedforwardFeedback);
        let inputs = [
            (0.0, 1.0, 50.0),
            (f32::NAN, 0.0, 50.0),
            (1.0, f32::INFINITY, 50.0),
            (0.0, 0.0, f32::NAN),
            (-1.0, 1.0, -1e9),
            (1e3, -1e3, 1e9),
        ];
        let mut last = state.output_v();
        for k in 0..600 {
            if k % 100 == 50 {
                state.set_mode(ServoMode::ALL[(k / 100) % 4]);
            }
            let (r, y, ff) = inputs[k % inputs.len()];
            let out = servo.step(&mut state, r, y, ff);
            assert!(out.voltage_v.is_finite() && (0.0..=120.0).contains(&out.voltage_v));
            assert!((out.voltage_v - last).abs() <= 10.0 + 1e-4);
            last = out.voltage_v;
        }
    }

    /// The filters follow the latency: at 10 kHz (τ = 1.5·T + 5 µs, 1/(4τ) = 1.6 kHz below the
    /// mode) the low-pass stays at f_n with the goal's notch; at 50 kHz (1/(4τ) = 7.1 kHz) it
    /// moves up and a wider notch wins, at the same margins; and when the goal allows a notch
    /// with lead, the 50 kHz loop holds the mode by phase at twice the 10 kHz crossover.
    #[test]
    fn a_faster_loop_moves_the_filters_and_raises_the_crossover() {
        let at_with = |rate: f32, goal: TuningGoal| {
            let t = 1.0 / rate;
            let dynamics = StageDynamics {
                gain_m_per_v: 3.4e-7,
                mode_frequency_hz: 3221.0,
                mode_damping: 0.03,
                latency_s: 1.5 * t + 5e-6,
            };
            let limits = CompensatorSettings {
                sample_period_s: t,
                ..limits()
            };
            tune(&dynamics, &goal, limits).unwrap()
        };
        let at = |rate: f32| at_with(rate, TuningGoal::default());
        let slow = at(10_000.0);
        let fast = at(50_000.0);
        // The low-pass moves up with the rate (the latency leaves the phase free), the notch
        // stays near the mode.
        assert!(
            fast.params.lowpass_frequency_hz > 2.0 * slow.params.lowpass_frequency_hz,
            "{slow:?} {fast:?}"
        );
        for t in [slow, fast] {
            assert!(
                t.phase_margin_deg >= 60.0
                    && t.phase_margin_deg < 180.0
                    && t.sensitivity_peak <= 1.6,
                "{t:?}"
            );
            let notch = t.params.notch_frequency_hz / 3221.0;
            assert!((0.8..=1.25).contains(&notch), "{t:?}");
        }
        assert!(
            fast.crossover_hz > 1.4 * slow.crossover_hz,
            "{slow:?} {fast:?}"
        );
        assert_eq!(fast.params.notch_pole_frequency_hz, 0.0, "{fast:?}");
        // At 50 kHz the latency leaves room to hold the mode by phase: a notch with lead, and
        // twice the crossover at the same margins; at 10 kHz the plain notch still wins.
        let by_phase = TuningGoal {
            mode_by_phase: true,
            ..TuningGoal::default()
        };
        assert_eq!(at_with(10_000.0, by_phase), slow);
        let lead = at_with(50_000.0, by_phase);
        assert!(
            lead.crossover_hz >= 2.0 * slow.crossover_hz
                && lead.phase_margin_deg >= 60.0
                && lead.sensitivity_peak <= 1.6,
            "{slow:?} {lead:?}"
        );
        assert!(
            lead.params.notch_pole_frequency_hz > lead.params.notch_frequency_hz,
            "{lead:?}"
        );
    }

    /// The closed loop in time, in f64: `servo` (feedback alone) at its period T on the plant
    /// `x'' = ω_n²·(g·u − x) − 2ζω_n·x'` with the mode at `scale`·f_n, semi-implicit Euler with
    /// 20 substeps per tick, the voltage computed from the tick's measurement applied one tick
    /// later plus `converter_s` (with the hold's half period, the latency the rule assumes), a
    /// 1 µm step of the reference at t = 0. Writes |r − x| per tick into `errors`.
    fn step_errors(
        servo: &Servo,
        dynamics: &StageDynamics,
        scale: f64,
        converter_s: f64,
        errors: &mut [f64],
    ) {
        let t = f64::from(servo.sample_period_s());
        let substeps = 20;
        let dt = t / f64::from(substeps);
        let late = libm::round(converter_s / dt) as u32;
        let wn = 2.0 * core::f64::consts::PI * f64::from(dynamics.mode_frequency_hz) * scale;
        let (zeta, g) = (
            f64::from(dynamics.mode_damping),
            f64::from(dynamics.gain_m_per_v),
        );
        let reference = 1e-6;
        let mut state = ServoState::at_rest(0.0, ServoMode::Feedback);
        let (mut x, mut v) = (0.0_f64, 0.0_f64);
        let (mut applied, mut next) = (0.0_f64, 0.0_f64);
        for error in errors.iter_mut() {
            *error = libm::fabs(reference - x);
            let out = servo.step(&mut state, reference as f32, x as f32, 0.0);
            for k in 0..substeps {
                if k == late {
                    applied = next;
                }
                v += dt * (wn * wn * (g * applied - x) - 2.0 * zeta * wn * v);
                x += dt * v;
            }
            next = f64::from(out.voltage_v);
        }
    }

    /// What the frequency rule accepts at 50 kHz when the goal allows it, the notch with lead
    /// holding the mode by phase with |L| > 1 around it, is stable in time, with the mode at f_n
    /// and ±10 %: a step settles within 1 nm; and with four times the gain, which the rule finds
    /// unstable (three times is still stable there, with |S| up to 8), the error does not decay
    /// (the window holds it in a limit cycle of tens of µm). With the mode 20 % low or absent it
    /// does not settle either, where the plain notch's loop does.
    #[test]
    fn a_notch_with_lead_holds_the_mode_in_time() {
        let t = 2e-5_f32;
        let converter_s = 5e-6;
        let dynamics = StageDynamics {
            gain_m_per_v: 3.3e-7,
            mode_frequency_hz: 2197.0,
            mode_damping: 0.03,
            latency_s: 1.5 * t + converter_s as f32,
        };
        let limits = CompensatorSettings {
            limits: Limits::new(-1000.0, 1000.0, 1e7),
            sample_period_s: t,
        };
        let by_phase = TuningGoal {
            mode_by_phase: true,
            ..TuningGoal::default()
        };
        let tuned = tune(&dynamics, &by_phase, limits).unwrap();
        assert!(tuned.params.notch_pole_frequency_hz > 0.0, "{tuned:?}");
        let servo = Servo::new(tuned.params, limits, dynamics.gain_m_per_v).unwrap();
        // |L| > 1 at the mode: held by phase, not by gain.
        let (re, im) = servo.response(f64::from(dynamics.mode_frequency_hz));
        let at_mode = dynamics
            .plant(f64::from(dynamics.mode_frequency_hz), 1.0)
            .mul(Complex { re, im });
        assert!(at_mode.abs() > 1.0, "{at_mode:?}");
        const TICKS: usize = 2500; // 50 ms
        let mut e = [0.0; TICKS];
        // The largest error over the last 10 ms of a step with the mode at `scale`·f_n.
        let mut tail_of = |servo: &Servo, scale: f64| {
            step_errors(servo, &dynamics, scale, converter_s, &mut e);
            e[TICKS - 500..].iter().fold(0.0_f64, |m, &x| m.max(x))
        };
        for scale in [1.0, 0.9, 1.1] {
            let tail = tail_of(&servo, scale);
            assert!(tail < 1e-9, "mode ×{scale}: {tail:e} m left of a 1 µm step");
        }
        let hot = Servo::new(
            ServoParams {
                ki_v_per_m_s: 4.0 * tuned.params.ki_v_per_m_s,
                ..tuned.params
            },
            limits,
            dynamics.gain_m_per_v,
        )
        .unwrap();
        let nyquist = 0.5 / f64::from(t);
        let low = f64::from(tuned.crossover_hz) / 100.0;
        assert!(margins(&hot, &dynamics, &[1.0], low, nyquist).is_none());
        let tail = tail_of(&hot, 1.0);
        assert!(tail > 1e-6, "{tail:e}");
        // The price: the mode 20 % below f_n (a payload) or far above it (a stage without
        // it) and the loop held by phase no longer settles, where the plain notch's does.
        let plain = tune(&dynamics, &TuningGoal::default(), limits).unwrap();
        let plain = Servo::new(plain.params, limits, dynamics.gain_m_per_v).unwrap();
        for scale in [0.8, 100.0] {
            let held = tail_of(&servo, scale);
            let gained = tail_of(&plain, scale);
            assert!(
                held > 1e-8 && gained < 1e-9,
                "mode ×{scale}: {held:e} vs {gained:e}"
            );
        }
    }

    /// The notch with lead: unit gain at DC, zero gain at its centre, (f_p/f_z)² at the
    /// Nyquist frequency (where the bilinear transform puts s = ∞), and the plain notch when its
    /// poles sit at its centre.
    #[test]
    fn a_notch_with_lead_is_what_the_doc_says() {
        let (fz, fp, q) = (2000.0_f32, 12_000.0_f32, 2.0_f32);
        let t = 2e-5_f32;
        let lead = notch_with_lead(fz, fp, q, t);
        let w = |hz: f64| 2.0 * core::f64::consts::PI * hz * f64::from(t);
        assert!(isclose(biquad_response(&lead, 0.0).abs(), 1.0, 1e-5, 0.0));
        assert!(biquad_response(&lead, w(f64::from(fz))).abs() < 1e-4);
        let hf = biquad_response(&lead, core::f64::consts::PI).abs();
        assert!(isclose(hf, f64::from(fp / fz).powi(2), 1e-4, 0.0), "{hf}");
        // Between the zero and the poles it leads.
        assert!(biquad_response(&lead, w(5000.0)).arg() > 0.5);
        let plain = rbj(fz, q, t, true);
        let same = notch_with_lead(fz, fz, q, t);
        for hz in [10.0, 500.0, 1900.0, 2100.0, 8000.0, 24_000.0] {
            let (a, b) = (
                biquad_response(&plain, w(hz)),
                biquad_response(&same, w(hz)),
            );
            assert!(isclose(a.abs(), b.abs(), 1e-4, 1e-6), "{hz}: {a:?} {b:?}");
        }
        // Poles without a notch are refused.
        let p = ServoParams {
            notch_frequency_hz: 0.0,
            notch_pole_frequency_hz: 5000.0,
            ..params()
        };
        assert!(Servo::new(p, limits(), G).is_err());
    }

    /// A loop whose phase passes −180° below its single crossover encircles −1: its margin
    /// read from the wrapped arg L would be above 180°, the unwrapped one is negative, and the
    /// rule refuses it (a wide notch and a low, low-Q low-pass at 10 kHz, crossing at f_n/2).
    #[test]
    fn a_loop_whose_phase_wraps_before_its_crossover_is_refused() {
        let dynamics = StageDynamics {
            gain_m_per_v: 3.4e-7,
            mode_frequency_hz: 3221.0,
            mode_damping: 0.03,
            latency_s: 1.5 * T,
        };
        let unit = ServoParams {
            kp_v_per_m: 0.0,
            ki_v_per_m_s: 1.0,
            lowpass_frequency_hz: 2255.0,
            lowpass_q: 0.5,
            notch_frequency_hz: 3221.0,
            notch_q: 0.35,
            notch_pole_frequency_hz: 0.0,
            transfer_time_constant_s: 0.02,
        };
        let fc = 1610.0;
        let probe = Servo::new(unit, limits(), G).unwrap();
        let (re, im) = probe.response(fc);
        let l1 = dynamics.plant(fc, 1.0).mul(Complex { re, im }).abs();
        let servo = Servo::new(
            ServoParams {
                ki_v_per_m_s: (1.0 / l1) as f32,
                ..unit
            },
            limits(),
            G,
        )
        .unwrap();
        let (re, im) = servo.response(fc);
        let l = dynamics.plant(fc, 1.0).mul(Complex { re, im });
        assert!(isclose(l.abs(), 1.0, 1e-3, 0.0));
        // The wrapped reading: a margin above 180°.
        assert!(180.0 + l.arg().to_degrees() > 180.0, "{}", l.arg());
        assert!(margins(&servo, &dynamics, &[1.0], fc / 100.0, 0.5 / f64::from(T)).is_none());
    }

    #[test]
    fn tuning_meets_its_goal_on_a_stage_like_the_xy_stage() {
        let dynamics = StageDynamics {
            gain_m_per_v: 0.75e-6,
            mode_frequency_hz: 2200.0,
            mode_damping: 0.024,
            latency_s: 1.5 * T,
        };
        let goal = TuningGoal::default();
        let tuning = tune(&dynamics, &goal, limits()).unwrap();
        assert!(tuning.phase_margin_deg >= 60.0, "{tuning:?}");
        assert!(tuning.sensitivity_peak <= 1.6, "{tuning:?}");
        assert!((100.0..1100.0).contains(&tuning.crossover_hz), "{tuning:?}");
        let notch = tuning.params.notch_frequency_hz / 2200.0;
        assert!((0.8..=1.25).contains(&notch), "{tuning:?}");
        assert!(tuning.params.ki_v_per_m_s > 0.0 && tuning.params.kp_v_per_m == 0.0);
        assert!(
            tuning.closed_loop_bandwidth_hz > tuning.crossover_hz,
            "{tuning:?}"
        );
        // A negative stage gain gives negative gains of the same size.
        let neg = StageDynamics {
            gain_m_per_v: -0.75e-6,
            ..dynamics
        };
        let t2 = tune(&neg, &goal, limits()).unwrap();
        assert_eq!(t2.params.ki_v_per_m_s, -tuning.params.ki_v_per_m_s);
        // A goal no loop can meet is refused.
        let impossible = TuningGoal {
            phase_margin_deg: 95.0,
            ..goal
        };
        assert!(tune(&dynamics, &impossible, limits()).is_err());
    }
}
