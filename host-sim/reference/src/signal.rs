//! Input signals u(t) with their time derivative u̇(t), breakpoints and a text spec parser.
//!
//! Every signal is exact in continuous time: sine, multisine and chirp are analytic; triangle, ramp-edged
//! square (seed 000, eq. 4) and raster are piecewise linear with breakpoints at their corners; staircase,
//! steps and zero-order-hold CSV data are piecewise constant and jump at their breakpoints; first-order-hold
//! CSV data is piecewise linear. `eval(t, left)` returns the left limit at a breakpoint when `left` is true,
//! so an integrator segment ending at a breakpoint never sees the value after the jump.

use std::f64::consts::PI;
use std::fmt;
use std::path::PathBuf;
use std::sync::atomic::{AtomicUsize, Ordering};

/// A scalar input signal in volts.
pub trait Signal: Send + Sync {
    /// (u in V, u̇ in V/s) at `t_s`; the left limit at a breakpoint when `left`.
    fn eval(&self, t_s: f64, left: bool) -> (f64, f64);
    /// Breakpoints (jumps, corners, reversals) in the half-open interval (t0, t1], ascending, appended to `out`.
    fn breakpoints(&self, t0_s: f64, t1_s: f64, out: &mut Vec<f64>);
    /// True when u is piecewise constant (u̇ = 0 between jumps).
    fn is_piecewise_constant(&self) -> bool {
        false
    }
    /// Value (right limit).
    fn value(&self, t_s: f64) -> f64 {
        self.eval(t_s, false).0
    }
}

/// Signal construction and parsing errors.
#[derive(Debug, Clone, PartialEq)]
pub enum SignalError {
    /// Unknown signal kind.
    UnknownKind {
        /// What was given.
        given: String,
    },
    /// Unknown key for a kind.
    UnknownKey {
        /// Signal kind.
        kind: String,
        /// What was given.
        key: String,
        /// Valid keys.
        valid: &'static str,
    },
    /// A value that is not a number, or out of range.
    BadValue {
        /// Key.
        key: String,
        /// What was given.
        given: String,
        /// Why it is wrong.
        reason: &'static str,
    },
    /// A required key is missing.
    MissingKey {
        /// Signal kind.
        kind: String,
        /// Key.
        key: &'static str,
    },
    /// CSV data problem.
    Csv(String),
}

impl fmt::Display for SignalError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::UnknownKind { given } => {
                write!(f, "unknown signal `{given}`; valid signals: {SIGNAL_KINDS}")
            }
            Self::UnknownKey { kind, key, valid } => {
                write!(
                    f,
                    "unknown key `{key}` for signal `{kind}`; valid keys: {valid}"
                )
            }
            Self::BadValue { key, given, reason } => {
                write!(f, "bad value `{given}` for `{key}`: {reason}")
            }
            Self::MissingKey { kind, key } => write!(f, "signal `{kind}` needs `{key}=...`"),
            Self::Csv(m) => write!(f, "{m}"),
        }
    }
}

impl std::error::Error for SignalError {}

/// Names of the signal kinds accepted by [`SignalSpec::parse`].
pub const SIGNAL_KINDS: &str =
    "sine, rising-sine, multisine, triangle, staircase, steps, square, chirp, raster, csv";

/// Help text for signal specs (used by the `host-sim` command line).
pub const SIGNAL_HELP: &str = "\
Signal spec: KIND:key=value,key=value,...  (lists use '/', e.g. levels=0/5/10)
  Units: U is the signal's own unit: stack volts for `simulate` and `link excite`, metres for
  `link track` and `link learn`, micrometres for `compensate --signal`; times in s, frequencies in Hz.
  common keys: duration (s), rate (Hz; the output sample rate, default: the plant's)
  sine        amp, offset (U), freq (Hz), phase_deg (deg)   u = offset + amp*sin(2*pi*freq*t + phase)
  rising-sine amp, offset (U), freq (Hz), phase_deg (deg), raised=0|1
                                                   u = offset + amp*(t/duration)*(sin(2*pi*freq*t + phase) + raised)
                                                   (amplitude rising from 0; raised=1, phase_deg=-90: valley at offset)
  multisine   offset (U), amps=a1/a2/.. (U), freqs=f1/f2/.. (Hz)   sum of sines (sine phases)
  triangle    low, high (U), freq (Hz)                 starts at low, rises first
  staircase   low, high, step (U), hold (s)            low->high->low in steps, each held `hold` (ZOH)
  steps       levels=l1/l2/.. (U), hold (s)            each level held `hold` (ZOH)
  square      low, amp (U), period, rise (s)           ramp-edged square (seed 000 eq. 4 defaults:
                                                   amp=7.8335 V, rise=1.8672e-6 s (a=4.1954 MV/s), period=1e-4 s)
  chirp       amp, offset (U), f0, f1 (Hz)             linear chirp f0->f1 over duration
  raster      x_low, x_high, y_low, y_high (U), line_freq (Hz)   two axes: x triangle, y slow ramp (xy-stage)
  csv         path, column (default u_V or ux_V; the column's suffix gives its unit; time t_s, t_ms, t_us or t_ns), hold=foh|zoh
Examples: sine:amp=10,offset=10,freq=2,phase_deg=-90,duration=1,rate=10000
          staircase:low=0,high=120,step=10,hold=0.03";

/// Sine u = offset + amp·sin(2π f t + φ); breakpoints at its reversals.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Sine {
    /// Amplitude, V.
    pub amplitude_v: f64,
    /// Offset, V.
    pub offset_v: f64,
    /// Frequency, Hz.
    pub frequency_hz: f64,
    /// Phase, rad.
    pub phase_rad: f64,
}

impl Signal for Sine {
    fn eval(&self, t: f64, _left: bool) -> (f64, f64) {
        let w = 2.0 * PI * self.frequency_hz;
        let p = w * t + self.phase_rad;
        (
            self.offset_v + self.amplitude_v * p.sin(),
            self.amplitude_v * w * p.cos(),
        )
    }
    fn breakpoints(&self, t0: f64, t1: f64, out: &mut Vec<f64>) {
        // Reversals where w t + φ = π/2 + kπ.
        if self.frequency_hz <= 0.0 {
            return;
        }
        let w = 2.0 * PI * self.frequency_hz;
        let k0 = ((w * t0 + self.phase_rad - PI / 2.0) / PI).floor() as i64;
        let mut k = k0;
        loop {
            let t = (PI / 2.0 + k as f64 * PI - self.phase_rad) / w;
            if t > t1 {
                break;
            }
            if t > t0 {
                out.push(t);
            }
            k += 1;
        }
    }
}

/// Rising-amplitude sine u = offset + a(t)·(sin(2π f t + φ) + r), a(t) = amp·min(t/T, 1), r = 1 when
/// raised (the wave rides on its own amplitude: with φ = −90° its valleys stay at the offset) else 0;
/// breakpoints at its reversals (u̇ = 0, found by Newton's method from the sine's).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct RisingSine {
    /// Final amplitude amp, V.
    pub amplitude_v: f64,
    /// Offset, V.
    pub offset_v: f64,
    /// Frequency, Hz.
    pub frequency_hz: f64,
    /// Phase, rad.
    pub phase_rad: f64,
    /// r: 1 (raised) or 0.
    pub raise: f64,
    /// T: the amplitude reaches amp at T, s.
    pub duration_s: f64,
}

impl RisingSine {
    /// (a, ȧ) at t.
    fn envelope(&self, t: f64) -> (f64, f64) {
        if t < self.duration_s {
            let rate = self.amplitude_v / self.duration_s;
            (rate * t.max(0.0), rate)
        } else {
            (self.amplitude_v, 0.0)
        }
    }
}

impl Signal for RisingSine {
    fn eval(&self, t: f64, _left: bool) -> (f64, f64) {
        let w = 2.0 * PI * self.frequency_hz;
        let p = w * t + self.phase_rad;
        let (a, da) = self.envelope(t);
        (
            self.offset_v + a * (p.sin() + self.raise),
            da * (p.sin() + self.raise) + a * w * p.cos(),
        )
    }
    fn breakpoints(&self, t0: f64, t1: f64, out: &mut Vec<f64>) {
        if self.frequency_hz <= 0.0 {
            return;
        }
        let w = 2.0 * PI * self.frequency_hz;
        let mut k = ((w * t0 + self.phase_rad - PI / 2.0) / PI).floor() as i64;
        loop {
            // From the sine's reversal, Newton on u̇(t) = 0 (u̇' by a central difference).
            let mut t = (PI / 2.0 + k as f64 * PI - self.phase_rad) / w;
            if t > t1 + 0.5 / self.frequency_hz {
                break;
            }
            let h = 1e-6 / self.frequency_hz;
            for _ in 0..8 {
                let d = self.eval(t, false).1;
                let dd = (self.eval(t + h, false).1 - self.eval(t - h, false).1) / (2.0 * h);
                if dd == 0.0 || !dd.is_finite() {
                    break;
                }
                t -= d / dd;
            }
            if t > t0 && t <= t1 && t.is_finite() {
                out.push(t);
            }
            k += 1;
        }
        out.sort_by(f64::total_cmp);
    }
}

/// Sum of sines around an offset.
#[derive(Debug, Clone, PartialEq)]
pub struct Multisine {
    /// Offset, V.
    pub offset_v: f64,
    /// (amplitude V, frequency Hz) pairs.
    pub components: Vec<(f64, f64)>,
}

impl Signal for Multisine {
    fn eval(&self, t: f64, _left: bool) -> (f64, f64) {
        let mut u = self.offset_v;
        let mut du = 0.0;
        for &(a, f) in &self.components {
            let w = 2.0 * PI * f;
            u += a * (w * t).sin();
            du += a * w * (w * t).cos();
        }
        (u, du)
    }
    fn breakpoints(&self, _t0: f64, _t1: f64, _out: &mut Vec<f64>) {}
}

/// Piecewise-linear signal through knots (t_i, u_i); constant outside. With `hold` it is a zero-order hold.
///
/// The knot search starts from the segment the previous query found (a cursor hint), so the
/// sequential queries of an integrator cost O(1) instead of a binary search; the result does not
/// depend on the hint.
#[derive(Debug)]
pub struct Piecewise {
    times_s: Vec<f64>,
    values_v: Vec<f64>,
    zero_order_hold: bool,
    /// The knot count ≤ t of the last query (a hint only: any value gives the same result).
    cursor: AtomicUsize,
}

impl Clone for Piecewise {
    fn clone(&self) -> Self {
        Self {
            times_s: self.times_s.clone(),
            values_v: self.values_v.clone(),
            zero_order_hold: self.zero_order_hold,
            cursor: AtomicUsize::new(self.cursor.load(Ordering::Relaxed)),
        }
    }
}

impl PartialEq for Piecewise {
    fn eq(&self, other: &Self) -> bool {
        self.times_s == other.times_s
            && self.values_v == other.values_v
            && self.zero_order_hold == other.zero_order_hold
    }
}

impl Piecewise {
    /// Knots must have strictly increasing, finite times; at least one knot.
    pub fn new(
        times_s: Vec<f64>,
        values_v: Vec<f64>,
        zero_order_hold: bool,
    ) -> Result<Self, SignalError> {
        if times_s.is_empty() || times_s.len() != values_v.len() {
            return Err(SignalError::Csv(
                "piecewise signal needs equal, non-empty time and value lists".into(),
            ));
        }
        if times_s.windows(2).any(|w| !(w[1] > w[0]))
            || times_s.iter().chain(&values_v).any(|v| !v.is_finite())
        {
            return Err(SignalError::Csv(
                "piecewise signal times must be finite and strictly increasing".into(),
            ));
        }
        Ok(Self {
            times_s,
            values_v,
            zero_order_hold,
            cursor: AtomicUsize::new(0),
        })
    }
    /// Knot times, s.
    pub fn times_s(&self) -> &[f64] {
        &self.times_s
    }
}

impl Signal for Piecewise {
    fn eval(&self, t: f64, left: bool) -> (f64, f64) {
        let ts = &self.times_s;
        // Segment index i: ts[i] <= t < ts[i+1] (right) or ts[i] < t <= ts[i+1] (left).
        let before = |b: f64| if left { b < t } else { b <= t };
        // idx = the number of knots `before` t (the partition point), tried at the hint and the
        // next knot first.
        let is_idx = |i: usize| (i == 0 || before(ts[i - 1])) && (i == ts.len() || !before(ts[i]));
        let hint = self.cursor.load(Ordering::Relaxed).min(ts.len());
        let idx = if is_idx(hint) {
            hint
        } else if hint < ts.len() && is_idx(hint + 1) {
            hint + 1
        } else {
            ts.partition_point(|&b| before(b))
        };
        self.cursor.store(idx, Ordering::Relaxed);
        if idx == 0 {
            return (self.values_v[0], 0.0);
        }
        let i = idx - 1;
        if i + 1 >= ts.len() {
            return (self.values_v[ts.len() - 1], 0.0);
        }
        if self.zero_order_hold {
            return (self.values_v[i], 0.0);
        }
        let slope = (self.values_v[i + 1] - self.values_v[i]) / (ts[i + 1] - ts[i]);
        (self.values_v[i] + slope * (t - ts[i]), slope)
    }
    fn breakpoints(&self, t0: f64, t1: f64, out: &mut Vec<f64>) {
        let start = self.times_s.partition_point(|&b| b <= t0);
        out.extend(self.times_s[start..].iter().take_while(|&&b| b <= t1));
    }
    fn is_piecewise_constant(&self) -> bool {
        self.zero_order_hold
    }
}

/// Periodic piecewise-linear waveform defined over one period by knots (phase s, value V); repeats.
#[derive(Debug, Clone, PartialEq)]
pub struct PeriodicPiecewise {
    period_s: f64,
    shape: Piecewise,
}

impl PeriodicPiecewise {
    /// `knots` cover [0, period] and the first and last value agree.
    pub fn new(period_s: f64, times_s: Vec<f64>, values_v: Vec<f64>) -> Result<Self, SignalError> {
        Ok(Self {
            period_s,
            shape: Piecewise::new(times_s, values_v, false)?,
        })
    }
    /// Triangle between low and high, rising first.
    pub fn triangle(low_v: f64, high_v: f64, frequency_hz: f64) -> Result<Self, SignalError> {
        let p = 1.0 / frequency_hz;
        Self::new(p, vec![0.0, p / 2.0, p], vec![low_v, high_v, low_v])
    }
    /// Square wave with ramp edges (seed 000 eq. 4): ramps from low to low+amp over `rise_s` at t = 0 and back
    /// at half period.
    pub fn ramp_square(
        low_v: f64,
        amplitude_v: f64,
        period_s: f64,
        rise_s: f64,
    ) -> Result<Self, SignalError> {
        let h = period_s / 2.0;
        Self::new(
            period_s,
            vec![0.0, rise_s, h, h + rise_s, period_s],
            vec![
                low_v,
                low_v + amplitude_v,
                low_v + amplitude_v,
                low_v,
                low_v,
            ],
        )
    }
}

impl Signal for PeriodicPiecewise {
    fn eval(&self, t: f64, left: bool) -> (f64, f64) {
        let k = (t / self.period_s).floor();
        let mut phase = t - k * self.period_s;
        if left && phase == 0.0 && t > 0.0 {
            phase = self.period_s;
        }
        self.shape.eval(phase, left)
    }
    fn breakpoints(&self, t0: f64, t1: f64, out: &mut Vec<f64>) {
        let mut k = (t0 / self.period_s).floor();
        loop {
            let base = k * self.period_s;
            if base > t1 {
                break;
            }
            for &p in &self.shape.times_s[..self.shape.times_s.len() - 1] {
                let t = base + p;
                if t > t0 && t <= t1 {
                    out.push(t);
                }
            }
            k += 1.0;
        }
    }
}

/// Linear chirp u = offset + amp·sin(2π(f0 t + (f1 − f0) t²/(2T))).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Chirp {
    /// Amplitude, V.
    pub amplitude_v: f64,
    /// Offset, V.
    pub offset_v: f64,
    /// Start frequency, Hz.
    pub start_hz: f64,
    /// End frequency, Hz.
    pub end_hz: f64,
    /// Sweep duration T, s.
    pub duration_s: f64,
}

impl Signal for Chirp {
    fn eval(&self, t: f64, _left: bool) -> (f64, f64) {
        let k = (self.end_hz - self.start_hz) / self.duration_s;
        let p = 2.0 * PI * (self.start_hz * t + 0.5 * k * t * t);
        let w = 2.0 * PI * (self.start_hz + k * t);
        (
            self.offset_v + self.amplitude_v * p.sin(),
            self.amplitude_v * w * p.cos(),
        )
    }
    fn breakpoints(&self, _t0: f64, _t1: f64, _out: &mut Vec<f64>) {}
}

/// Zero-order-hold staircase low → high → low in `step` increments, each level held `hold_s`.
pub fn staircase(
    low_v: f64,
    high_v: f64,
    step_v: f64,
    hold_s: f64,
) -> Result<Piecewise, SignalError> {
    if !(step_v > 0.0) || !(high_v > low_v) || !(hold_s > 0.0) {
        return Err(SignalError::BadValue {
            key: "step/high/hold".into(),
            given: format!("step={step_v}, low={low_v}, high={high_v}, hold={hold_s}"),
            reason: "need step > 0, high > low, hold > 0",
        });
    }
    let n = ((high_v - low_v) / step_v).round() as usize;
    let mut levels: Vec<f64> = (0..=n)
        .map(|i| (low_v + i as f64 * step_v).min(high_v))
        .collect();
    let down: Vec<f64> = levels.iter().rev().skip(1).copied().collect();
    levels.extend(down);
    steps(&levels, hold_s)
}

/// Zero-order-hold steps: `levels[i]` from i·hold to (i+1)·hold, last level held afterwards.
pub fn steps(levels_v: &[f64], hold_s: f64) -> Result<Piecewise, SignalError> {
    let times = (0..levels_v.len()).map(|i| i as f64 * hold_s).collect();
    Piecewise::new(times, levels_v.to_vec(), true)
}

/// Which signal, with its parameters; built into one [`Signal`] per plant input by [`SignalSpec::build`].
#[derive(Debug, Clone, PartialEq)]
pub enum SignalKind {
    /// See [`Sine`].
    Sine(Sine),
    /// See [`RisingSine`].
    RisingSine(RisingSine),
    /// See [`Multisine`].
    Multisine(Multisine),
    /// Triangle low..high at freq.
    Triangle {
        /// V.
        low_v: f64,
        /// V.
        high_v: f64,
        /// Hz.
        frequency_hz: f64,
    },
    /// See [`staircase`].
    Staircase {
        /// V.
        low_v: f64,
        /// V.
        high_v: f64,
        /// V.
        step_v: f64,
        /// s.
        hold_s: f64,
    },
    /// See [`steps`].
    Steps {
        /// V.
        levels_v: Vec<f64>,
        /// s.
        hold_s: f64,
    },
    /// Ramp-edged square (seed 000 eq. 4).
    Square {
        /// V.
        low_v: f64,
        /// V.
        amplitude_v: f64,
        /// s.
        period_s: f64,
        /// s.
        rise_s: f64,
    },
    /// See [`Chirp`].
    Chirp(Chirp),
    /// Two-axis raster: x triangle at line frequency, y linear ramp over the duration.
    Raster {
        /// V.
        x_low_v: f64,
        /// V.
        x_high_v: f64,
        /// Hz.
        line_hz: f64,
        /// V.
        y_low_v: f64,
        /// V.
        y_high_v: f64,
    },
    /// Samples from a CSV file (its `t_s`, or `t_ms`, `t_us`, `t_ns`, a record's time base,
    /// `crate::csv::Rows::time`).
    Csv {
        /// File.
        path: PathBuf,
        /// The end of the file's samples \[s\]: its last time plus its last step (a file of N
        /// samples at rate f from 0 plays N/f seconds), the signal's natural duration.
        end_s: f64,
        /// Column name.
        column: Option<String>,
        /// Zero-order hold (else first-order hold).
        zero_order_hold: bool,
    },
}

/// A parsed signal spec.
#[derive(Debug, Clone, PartialEq)]
pub struct SignalSpec {
    /// The waveform.
    pub kind: SignalKind,
    /// Simulated duration, s (None: the signal's natural length or 1 s).
    pub duration_s: Option<f64>,
    /// Output sample rate, Hz (None: the plant's default).
    pub sample_rate_hz: Option<f64>,
}

struct Kv<'a> {
    kind: &'a str,
    pairs: Vec<(&'a str, &'a str)>,
    used: Vec<bool>,
}

impl<'a> Kv<'a> {
    fn get(&mut self, key: &str) -> Option<&'a str> {
        let i = self.pairs.iter().position(|(k, _)| *k == key)?;
        self.used[i] = true;
        Some(self.pairs[i].1)
    }
    fn num(&mut self, key: &str, default: Option<f64>) -> Result<f64, SignalError> {
        match self.get(key) {
            Some(v) => parse_num(key, v),
            None => default.ok_or(SignalError::MissingKey {
                kind: self.kind.to_string(),
                key: leak_key(key),
            }),
        }
    }
    fn list(&mut self, key: &str) -> Result<Vec<f64>, SignalError> {
        let v = self.get(key).ok_or(SignalError::MissingKey {
            kind: self.kind.to_string(),
            key: leak_key(key),
        })?;
        v.split('/').map(|s| parse_num(key, s)).collect()
    }
}

fn leak_key(key: &str) -> &'static str {
    // Keys come from the fixed tables below; map to their static spelling.
    const KEYS: [&str; 8] = [
        "amps", "freqs", "levels", "path", "hold", "step", "high", "freq",
    ];
    KEYS.iter().find(|k| **k == key).copied().unwrap_or("value")
}

fn parse_num(key: &str, v: &str) -> Result<f64, SignalError> {
    let x: f64 = v.trim().parse().map_err(|_| SignalError::BadValue {
        key: key.to_string(),
        given: v.to_string(),
        reason: "not a number",
    })?;
    if !x.is_finite() {
        return Err(SignalError::BadValue {
            key: key.to_string(),
            given: v.to_string(),
            reason: "not finite",
        });
    }
    Ok(x)
}

fn positive(key: &str, x: f64) -> Result<f64, SignalError> {
    if x > 0.0 {
        Ok(x)
    } else {
        Err(SignalError::BadValue {
            key: key.into(),
            given: x.to_string(),
            reason: "must be > 0",
        })
    }
}

/// The signal of `kind` from its keys, and the keys it takes (for the unknown-key error).
fn signal_kind(
    kind: &str,
    kv: &mut Kv,
    duration_s: Option<f64>,
) -> Result<(SignalKind, &'static str), SignalError> {
    let kind_and_keys = match kind {
        "sine" => (
            SignalKind::Sine(Sine {
                amplitude_v: kv.num("amp", Some(1.0))?,
                offset_v: kv.num("offset", Some(0.0))?,
                frequency_hz: positive("freq", kv.num("freq", Some(1.0))?)?,
                phase_rad: kv.num("phase_deg", Some(0.0))?.to_radians(),
            }),
            "amp, offset, freq, phase_deg, duration, rate",
        ),
        "rising-sine" => {
            let raise = kv.num("raised", Some(0.0))?;
            if raise != 0.0 && raise != 1.0 {
                return Err(SignalError::BadValue {
                    key: "raised".into(),
                    given: raise.to_string(),
                    reason: "0 or 1",
                });
            }
            (
                SignalKind::RisingSine(RisingSine {
                    amplitude_v: kv.num("amp", Some(1.0))?,
                    offset_v: kv.num("offset", Some(0.0))?,
                    frequency_hz: positive("freq", kv.num("freq", Some(1.0))?)?,
                    phase_rad: kv.num("phase_deg", Some(0.0))?.to_radians(),
                    raise,
                    duration_s: positive("duration", duration_s.unwrap_or(1.0))?,
                }),
                "amp, offset, freq, phase_deg, raised, duration, rate",
            )
        }
        "multisine" => {
            let amps = kv.list("amps")?;
            let freqs = kv.list("freqs")?;
            if amps.len() != freqs.len() {
                return Err(SignalError::BadValue {
                    key: "amps/freqs".into(),
                    given: format!("{} amplitudes, {} frequencies", amps.len(), freqs.len()),
                    reason: "lists must have the same length",
                });
            }
            (
                SignalKind::Multisine(Multisine {
                    offset_v: kv.num("offset", Some(0.0))?,
                    components: amps.into_iter().zip(freqs).collect(),
                }),
                "offset, amps, freqs, duration, rate",
            )
        }
        "triangle" => (
            SignalKind::Triangle {
                low_v: kv.num("low", Some(0.0))?,
                high_v: kv.num("high", Some(1.0))?,
                frequency_hz: positive("freq", kv.num("freq", Some(1.0))?)?,
            },
            "low, high, freq, duration, rate",
        ),
        "staircase" => (
            SignalKind::Staircase {
                low_v: kv.num("low", Some(0.0))?,
                high_v: kv.num("high", None)?,
                step_v: positive("step", kv.num("step", None)?)?,
                hold_s: positive("hold", kv.num("hold", None)?)?,
            },
            "low, high, step, hold, duration, rate",
        ),
        "steps" => (
            SignalKind::Steps {
                levels_v: kv.list("levels")?,
                hold_s: positive("hold", kv.num("hold", None)?)?,
            },
            "levels, hold, duration, rate",
        ),
        "square" => (
            SignalKind::Square {
                low_v: kv.num("low", Some(0.0))?,
                amplitude_v: kv.num("amp", Some(7.8335))?,
                period_s: positive("period", kv.num("period", Some(1e-4))?)?,
                rise_s: positive("rise", kv.num("rise", Some(1.8672e-6))?)?,
            },
            "low, amp, period, rise, duration, rate",
        ),
        "chirp" => (
            SignalKind::Chirp(Chirp {
                amplitude_v: kv.num("amp", Some(1.0))?,
                offset_v: kv.num("offset", Some(0.0))?,
                start_hz: kv.num("f0", Some(1.0))?,
                end_hz: kv.num("f1", Some(100.0))?,
                duration_s: duration_s.unwrap_or(1.0),
            }),
            "amp, offset, f0, f1, duration, rate",
        ),
        "raster" => (
            SignalKind::Raster {
                x_low_v: kv.num("x_low", Some(0.0))?,
                x_high_v: kv.num("x_high", Some(100.0))?,
                line_hz: positive("line_freq", kv.num("line_freq", Some(10.0))?)?,
                y_low_v: kv.num("y_low", Some(0.0))?,
                y_high_v: kv.num("y_high", Some(100.0))?,
            },
            "x_low, x_high, line_freq, y_low, y_high, duration, rate",
        ),
        "csv" => {
            let path = PathBuf::from(kv.get("path").ok_or(SignalError::MissingKey {
                kind: "csv".into(),
                key: "path",
            })?);
            // The file's samples cover [t0, t_last + T): its last step past its last time.
            let t = csv_times(&path)?;
            let end_s = match t.as_slice() {
                [.., a, b] => b + (b - a),
                _ => 0.0,
            };
            (
                SignalKind::Csv {
                    path,
                    end_s,
                    column: kv.get("column").map(str::to_string),
                    zero_order_hold: match kv.get("hold") {
                        None | Some("foh") => false,
                        Some("zoh") => true,
                        Some(other) => {
                            return Err(SignalError::BadValue {
                                key: "hold".into(),
                                given: other.into(),
                                reason: "valid: foh, zoh",
                            })
                        }
                    },
                },
                "path, column, hold, duration, rate",
            )
        }
        other => {
            return Err(SignalError::UnknownKind {
                given: other.to_string(),
            })
        }
    };
    Ok(kind_and_keys)
}

/// The `t_s` column of a CSV signal file, checked as a record's time base; with the rows.
fn csv_rows(path: &std::path::Path) -> Result<(crate::csv::Rows, Vec<f64>), SignalError> {
    let csv = |e: crate::csv::CsvError| SignalError::Csv(e.to_string());
    let rows = crate::csv::read_rows(path).map_err(csv)?;
    // The time base in the unit its suffix names (`t_s`, `t_ms`, `t_us`/`t_µs`, `t_ns`), in
    // seconds; without one, the error for `t_s`.
    let (name, factor) = rows
        .table
        .names
        .iter()
        .find_map(|n| time_unit_factor(n).map(|f| (n.clone(), f)))
        .unwrap_or_else(|| ("t_s".to_string(), 1.0));
    let t = rows
        .time(&name, factor)
        .map_err(csv)?
        .iter()
        .map(|t| t * factor)
        .collect();
    Ok((rows, t))
}

/// Seconds per unit of a time column named `t_<unit>` (`s`, `ms`, `us` or `µs`, `ns`).
fn time_unit_factor(name: &str) -> Option<f64> {
    match name.strip_prefix("t_")? {
        "s" => Some(1.0),
        "ms" => Some(1e-3),
        "us" | "µs" => Some(1e-6),
        "ns" => Some(1e-9),
        _ => None,
    }
}

fn csv_times(path: &std::path::Path) -> Result<Vec<f64>, SignalError> {
    csv_rows(path).map(|(_, t)| t)
}

impl SignalSpec {
    /// Parses `kind:key=value,...` (see [`SIGNAL_HELP`]).
    pub fn parse(spec: &str) -> Result<Self, SignalError> {
        let (kind, rest) = spec.split_once(':').unwrap_or((spec, ""));
        let kind = kind.trim();
        let mut pairs = Vec::new();
        for item in rest.split(',').filter(|s| !s.trim().is_empty()) {
            let (k, v) = item.split_once('=').ok_or(SignalError::BadValue {
                key: item.to_string(),
                given: item.to_string(),
                reason: "expected key=value",
            })?;
            pairs.push((k.trim(), v.trim()));
        }
        let used = vec![false; pairs.len()];
        let mut kv = Kv { kind, pairs, used };
        let duration_s = kv
            .get("duration")
            .map(|v| parse_num("duration", v).and_then(|x| positive("duration", x)))
            .transpose()?;
        let sample_rate_hz = kv
            .get("rate")
            .map(|v| parse_num("rate", v).and_then(|x| positive("rate", x)))
            .transpose()?;
        let (kind_value, valid) = signal_kind(kind, &mut kv, duration_s)?;
        if let Some(i) = kv.used.iter().position(|u| !u) {
            return Err(SignalError::UnknownKey {
                kind: kind.to_string(),
                key: kv.pairs[i].0.to_string(),
                valid,
            });
        }
        Ok(Self {
            kind: kind_value,
            duration_s,
            sample_rate_hz,
        })
    }

    /// The end of a `csv` signal's file \[s\]: its last time plus its last step (`None` for the
    /// other kinds).
    pub fn csv_end_s(&self) -> Option<f64> {
        match &self.kind {
            SignalKind::Csv { end_s, .. } => Some(*end_s),
            _ => None,
        }
    }

    /// Natural duration of the signal (staircase/steps: all levels; square: two periods; csv: the
    /// whole file, to its last time plus its last step), else 1 s.
    pub fn default_duration_s(&self) -> f64 {
        match &self.kind {
            SignalKind::Staircase {
                low_v,
                high_v,
                step_v,
                hold_s,
            } => {
                let n = ((high_v - low_v) / step_v).round();
                (2.0 * n + 1.0) * hold_s
            }
            SignalKind::Steps { levels_v, hold_s } => levels_v.len() as f64 * hold_s,
            SignalKind::Square { period_s, .. } => 2.0 * period_s,
            SignalKind::Csv { end_s, .. } => *end_s,
            _ => 1.0,
        }
    }

    /// Builds one signal per plant input: single-axis signals are repeated on every input; a raster needs
    /// two inputs.
    pub fn build(&self, inputs: usize) -> Result<Vec<Box<dyn Signal>>, SignalError> {
        let one: Box<dyn Signal> = match &self.kind {
            SignalKind::Sine(s) => Box::new(*s),
            SignalKind::RisingSine(s) => Box::new(*s),
            SignalKind::Multisine(m) => Box::new(m.clone()),
            SignalKind::Triangle {
                low_v,
                high_v,
                frequency_hz,
            } => Box::new(PeriodicPiecewise::triangle(*low_v, *high_v, *frequency_hz)?),
            SignalKind::Staircase {
                low_v,
                high_v,
                step_v,
                hold_s,
            } => Box::new(staircase(*low_v, *high_v, *step_v, *hold_s)?),
            SignalKind::Steps { levels_v, hold_s } => Box::new(steps(levels_v, *hold_s)?),
            SignalKind::Square {
                low_v,
                amplitude_v,
                period_s,
                rise_s,
            } => {
                if 2.0 * rise_s >= *period_s {
                    return Err(SignalError::BadValue {
                        key: "rise".into(),
                        given: rise_s.to_string(),
                        reason: "rise must be shorter than half the period",
                    });
                }
                Box::new(PeriodicPiecewise::ramp_square(
                    *low_v,
                    *amplitude_v,
                    *period_s,
                    *rise_s,
                )?)
            }
            SignalKind::Chirp(c) => Box::new(*c),
            SignalKind::Raster {
                x_low_v,
                x_high_v,
                line_hz,
                y_low_v,
                y_high_v,
            } => {
                if inputs != 2 {
                    return Err(SignalError::BadValue {
                        key: "raster".into(),
                        given: format!("{inputs} plant input(s)"),
                        reason: "a raster drives two axes (use --plant xy-stage)",
                    });
                }
                let d = self.duration_s.unwrap_or(1.0);
                return Ok(vec![
                    Box::new(PeriodicPiecewise::triangle(*x_low_v, *x_high_v, *line_hz)?),
                    Box::new(Piecewise::new(
                        vec![0.0, d],
                        vec![*y_low_v, *y_high_v],
                        false,
                    )?),
                ]);
            }
            SignalKind::Csv {
                path,
                column,
                zero_order_hold,
                ..
            } => {
                let (rows, t) = csv_rows(path)?;
                let table = rows.table;
                if inputs == 2 && column.is_none() {
                    let mut out: Vec<Box<dyn Signal>> = Vec::new();
                    for name in ["ux_V", "uy_V"] {
                        let u = table
                            .column(name)
                            .map_err(|e| SignalError::Csv(e.to_string()))?
                            .to_vec();
                        out.push(Box::new(Piecewise::new(t.clone(), u, *zero_order_hold)?));
                    }
                    return Ok(out);
                }
                let name =
                    column
                        .as_deref()
                        .unwrap_or(if table.has("u_V") { "u_V" } else { "ux_V" });
                let u = table
                    .column(name)
                    .map_err(|e| SignalError::Csv(e.to_string()))?
                    .to_vec();
                Box::new(Piecewise::new(t, u, *zero_order_hold)?)
            }
        };
        let mut out = vec![one];
        for _ in 1..inputs {
            let again = Self {
                kind: self.kind.clone(),
                ..self.clone()
            }
            .build(1)?;
            out.extend(again);
        }
        Ok(out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn numeric_derivative(s: &dyn Signal, t: f64) -> f64 {
        let e = 1e-7;
        (s.value(t + e) - s.value(t - e)) / (2.0 * e)
    }

    #[test]
    fn derivatives_match_finite_differences() {
        let sigs: Vec<Box<dyn Signal>> = vec![
            Box::new(Sine {
                amplitude_v: 10.0,
                offset_v: 10.0,
                frequency_hz: 2.0,
                phase_rad: -PI / 2.0,
            }),
            Box::new(Multisine {
                offset_v: 1.0,
                components: vec![(1.0, 3.0), (0.5, 7.0)],
            }),
            Box::new(Chirp {
                amplitude_v: 2.0,
                offset_v: 0.0,
                start_hz: 1.0,
                end_hz: 20.0,
                duration_s: 1.0,
            }),
            Box::new(PeriodicPiecewise::triangle(0.0, 5.0, 3.0).unwrap()),
        ];
        for s in &sigs {
            for &t in &[0.0123, 0.31, 0.77] {
                let (_, du) = s.eval(t, false);
                assert!(
                    (du - numeric_derivative(s.as_ref(), t)).abs() < 1e-4 * (1.0 + du.abs()),
                    "t={t}"
                );
            }
        }
    }

    #[test]
    fn stage_cosine_is_sine_with_minus_90_degrees() {
        let s = SignalSpec::parse("sine:amp=10,offset=10,freq=2,phase_deg=-90")
            .unwrap()
            .build(1)
            .unwrap();
        for &t in &[0.0, 0.1, 0.37] {
            assert!((s[0].value(t) - (10.0 - 10.0 * (4.0 * PI * t).cos())).abs() < 1e-12);
        }
        let mut bp = Vec::new();
        s[0].breakpoints(0.0, 1.0, &mut bp);
        assert_eq!(bp.len(), 4); // maxima at 0.25, 0.75, minima at 0.5, 1.0
        assert!((bp[0] - 0.25).abs() < 1e-12);
    }

    #[test]
    fn ramp_square_matches_seed_000_eq4() {
        let s = PeriodicPiecewise::ramp_square(0.0, 7.8335, 1e-4, 1.8672e-6).unwrap();
        let slope: f64 = 7.8335 / 1.8672e-6;
        assert!((slope - 4.1954e6).abs() / 4.1954e6 < 1e-3);
        assert!((s.eval(1e-6, false).1 - slope).abs() < 1e-6 * slope);
        assert_eq!(s.value(2e-5), 7.8335);
        assert_eq!(s.value(9e-5), 0.0);
        assert!((s.eval(5e-5 + 1e-6, false).1 + slope).abs() < 1e-6 * slope);
    }

    #[test]
    fn piecewise_cursor_gives_the_binary_search_result_in_any_order() {
        let times: Vec<f64> = (0..50).map(|k| k as f64 * 0.1).collect();
        let values: Vec<f64> = (0..50).map(|k| ((k * 37) % 11) as f64).collect();
        for hold in [true, false] {
            let s = Piecewise::new(times.clone(), values.clone(), hold).unwrap();
            let reference = |t: f64, left: bool| {
                let fresh = Piecewise::new(times.clone(), values.clone(), hold).unwrap();
                fresh.eval(t, left)
            };
            // Forward, backward and scattered queries, on knots and between them, both limits.
            let mut queries: Vec<f64> = (-3..60).map(|k| k as f64 * 0.05).collect();
            queries.extend((-3..60).rev().map(|k| k as f64 * 0.1));
            queries.extend((0..200).map(|k| ((k * 7919) % 613) as f64 * 0.01 - 0.5));
            for &t in &queries {
                for left in [false, true] {
                    assert_eq!(
                        s.eval(t, left),
                        reference(t, left),
                        "t = {t}, left = {left}"
                    );
                }
            }
        }
    }

    #[test]
    fn staircase_left_and_right_limits() {
        let s = staircase(0.0, 120.0, 10.0, 0.03).unwrap();
        assert_eq!(s.eval(0.03, true).0, 0.0);
        assert_eq!(s.eval(0.03, false).0, 10.0);
        assert_eq!(s.value(12.5 * 0.03), 120.0);
        assert_eq!(s.value(24.5 * 0.03), 0.0);
        let mut bp = Vec::new();
        s.breakpoints(0.0, 0.1, &mut bp);
        assert_eq!(bp.len(), 3);
        assert!(s.is_piecewise_constant());
    }

    #[test]
    fn parse_errors_name_key_and_choices() {
        let e = SignalSpec::parse("sinus:amp=1").unwrap_err().to_string();
        assert!(e.contains("sinus") && e.contains("staircase"), "{e}");
        let e = SignalSpec::parse("sine:amp=abc").unwrap_err().to_string();
        assert!(e.contains("amp") && e.contains("abc"), "{e}");
        let e = SignalSpec::parse("sine:ampl=1").unwrap_err().to_string();
        assert!(e.contains("ampl") && e.contains("phase_deg"), "{e}");
        assert!(SignalSpec::parse("staircase:high=12,step=1").is_err());
    }

    #[test]
    fn raster_gives_two_axes() {
        let s = SignalSpec::parse("raster:x_high=50,y_high=20,line_freq=10,duration=1").unwrap();
        let sig = s.build(2).unwrap();
        assert_eq!(sig.len(), 2);
        assert!((sig[0].value(0.05) - 50.0).abs() < 1e-9);
        assert!((sig[1].value(0.5) - 10.0).abs() < 1e-9);
        assert!(s.build(1).is_err());
    }

    /// A `csv:` signal's time column is read in the unit its suffix names: `t_ms` plays as the
    /// same file in `t_s`, where it was refused for lacking `t_s`; a unit no time has is refused,
    /// naming the file, its line and the column.
    #[test]
    fn a_csv_signal_reads_its_time_in_the_unit_its_suffix_names() {
        let dir = tempfile::tempdir().unwrap();
        let write = |name: &str, header: &str, scale: f64| {
            let path = dir.path().join(name);
            let mut text = format!("{header},u_V\n");
            for k in 0..20 {
                text += &format!("{},{}\n", k as f64 * 1e-3 * scale, (k * k) as f64 * 0.1);
            }
            std::fs::write(&path, text).unwrap();
            path
        };
        let in_s = write("s.csv", "t_s", 1.0);
        let in_ms = write("ms.csv", "t_ms", 1e3);
        let play = |path: &std::path::Path| {
            let spec = SignalSpec::parse(&format!("csv:path={}", path.display())).unwrap();
            let signal = spec.build(1).unwrap().remove(0);
            (
                spec.csv_end_s(),
                [0.0, 0.0041, 0.0105, 0.019].map(|t| signal.value(t)),
            )
        };
        let (end_s, values) = play(&in_s);
        let (end_ms, values_ms) = play(&in_ms);
        let (end_s, end_ms) = (end_s.unwrap(), end_ms.unwrap());
        assert!(
            (end_s - 0.02).abs() < 1e-12 && (end_ms - end_s).abs() < 1e-12,
            "{end_ms}"
        );
        for (a, b) in values.iter().zip(values_ms) {
            assert!((a - b).abs() < 1e-9, "{values:?} against {values_ms:?}");
        }
        let other = write("min.csv", "t_min", 1.0);
        let err = SignalSpec::parse(&format!("csv:path={}", other.display()))
            .and_then(|spec| spec.build(1).map(|_| ()))
            .unwrap_err()
            .to_string();
        assert!(
            err.contains("min.csv:1") && err.contains("`t_min`"),
            "{err}"
        );
    }
}
