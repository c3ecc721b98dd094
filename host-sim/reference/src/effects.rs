//! Effects that real data carry and none of the source models declares (MODELS.md, "What is not in any of
//! the papers"). Each is off by default, switchable, and parsed from `name:key=value,...`.
//!
//! - `creep`: bank of Kelvin–Voigt elements in series with the actuator, ċ_i = (w_i·y_free − c_i)/τ_i, added
//!   to every output (y_free = quasi-static actuator displacement of the plant). Decades of τ approximate the
//!   logarithmic creep of piezo stacks.
//! - `drift`: slow thermal drift y += rate·t + amplitude·(1 − e^(−t/τ)).
//! - `delay`: sensor delay, y_meas(t) = y(t − d) by linear interpolation between output samples.
//! - `amplifier`: first-order amplifier v̇ = clamp(2π·f_c·(u − v), ±slew) between command and actuator.
//! - `noise`: white Gaussian sensor noise, seeded ChaCha8 (deterministic).
//! - `adc`: output quantisation to `lsb` metres.
//! - `dac`: command sampled at `rate` Hz, held (zero-order hold) and quantised to `bits` over [min, max] V.
//! - `electrostriction`: quadratic term, the linear drive k·u becomes k·(u + e·u²).
//! - `coupling` (xy-stage): measured x += xy·y, measured y += yx·x.
//! - `dielectric-lag` (xy-stage, stage): rate-dependent hysteresis, the stacks' Bouc-Wen operator driven by a
//!   first-order lag of the stack voltage (τ_v·v̇ = u − v), the linear strain by u itself; see
//!   [`crate::plant::XyStage`].
//! - `rate-bouc-wen` (xy-stage, stage): rate-dependent hysteresis, the stacks' Bouc-Wen gain growing with
//!   the input's speed, α·(1 + |u̇|/ṙ₀); see [`crate::plant::XyStage`].
//! - `second-mode` (nac2024): second resonance mode, see [`crate::plant::SecondMode`].

use crate::plant::{PlantError, PlantKind, SecondMode};
use crate::signal::Signal;
use std::fmt;

/// Effect names accepted by [`Effects::add_spec`].
pub const EFFECT_NAMES: &str =
    "creep, drift, delay, amplifier, noise, adc, dac, electrostriction, coupling, dielectric-lag, rate-bouc-wen, second-mode";

/// Help text for effect specs.
pub const EFFECT_HELP: &str = "\
Effect spec: NAME:key=value,...  (repeat --effect for several; lists use '/')
  creep             tau=0.1/1/10 (s), weight=0.01/0.01/0.01   Kelvin-Voigt creep bank
  drift             rate (m/s, 1e-9), amplitude (m, 0), tau (s, 60)
  delay             s (sensor delay, 1e-5)
  amplifier         bandwidth_hz (1e4), slew_v_per_s (inf)
  noise             rms_m (1e-9), seed (1)
  adc               lsb_m (1e-9)
  dac               bits (16), min (0 V), max (120 V), rate_hz (1e5)
  electrostriction  per_v (1e-3)
  coupling          xy (0.01), yx (0.01)                       xy-stage only
  dielectric-lag    tau (s, 1e-3): Bouc-Wen driven by a lag of the stack voltage   xy-stage, stage
  rate-bouc-wen     rate (V/s, 1e5): Bouc-Wen gain alpha*(1 + |rate|/rate0)       xy-stage, stage
  second-mode       freq_hz (480e3), zeta (0.05), participation (0.05)   nac2024 only";

/// Effect errors.
#[derive(Debug, Clone, PartialEq)]
pub enum EffectError {
    /// Unknown effect name.
    UnknownEffect {
        /// Given.
        given: String,
    },
    /// Unknown key.
    UnknownKey {
        /// Effect.
        effect: String,
        /// Key.
        key: String,
        /// Valid keys.
        valid: &'static str,
    },
    /// Bad number.
    BadValue {
        /// Key.
        key: String,
        /// Given.
        given: String,
        /// Why.
        reason: &'static str,
    },
}

impl fmt::Display for EffectError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            Self::UnknownEffect { given } => {
                write!(f, "unknown effect `{given}`; valid effects: {EFFECT_NAMES}")
            }
            Self::UnknownKey { effect, key, valid } => {
                write!(
                    f,
                    "unknown key `{key}` for effect `{effect}`; valid keys: {valid}"
                )
            }
            Self::BadValue { key, given, reason } => {
                write!(f, "bad value `{given}` for `{key}`: {reason}")
            }
        }
    }
}

impl std::error::Error for EffectError {}

/// Kelvin–Voigt creep bank.
#[derive(Debug, Clone, PartialEq)]
pub struct Creep {
    /// (time constant s, weight) per element.
    pub elements: Vec<(f64, f64)>,
}

/// Thermal drift.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ThermalDrift {
    /// Linear rate, m/s.
    pub rate_m_per_s: f64,
    /// Exponential settling amplitude, m.
    pub amplitude_m: f64,
    /// Settling time constant, s.
    pub time_constant_s: f64,
}

impl ThermalDrift {
    /// Drift at `t_s`.
    pub fn at(&self, t_s: f64) -> f64 {
        self.rate_m_per_s * t_s + self.amplitude_m * (1.0 - (-t_s / self.time_constant_s).exp())
    }
}

/// First-order amplifier with slew limit.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Amplifier {
    /// −3 dB bandwidth, Hz.
    pub bandwidth_hz: f64,
    /// Slew limit, V/s (infinite: none).
    pub slew_v_per_s: f64,
}

impl Amplifier {
    /// v̇ for command `u` and output `v`.
    pub fn rate(&self, u: f64, v: f64) -> f64 {
        (2.0 * std::f64::consts::PI * self.bandwidth_hz * (u - v))
            .clamp(-self.slew_v_per_s, self.slew_v_per_s)
    }
}

/// Gaussian sensor noise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SensorNoise {
    /// Standard deviation, m.
    pub rms_m: f64,
    /// RNG seed.
    pub seed: u64,
}

/// DAC: sample, hold, quantise.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Dac {
    /// Resolution, bits.
    pub bits: u32,
    /// Lowest code voltage, V.
    pub min_v: f64,
    /// Highest code voltage, V.
    pub max_v: f64,
    /// Update rate, Hz.
    pub rate_hz: f64,
}

impl Dac {
    /// Volts per LSB.
    pub fn lsb_v(&self) -> f64 {
        (self.max_v - self.min_v) / ((1u64 << self.bits) - 1) as f64
    }
    /// Quantised, clamped value.
    pub fn quantise(&self, u: f64) -> f64 {
        let lsb = self.lsb_v();
        self.min_v + ((u.clamp(self.min_v, self.max_v) - self.min_v) / lsb).round() * lsb
    }
}

/// A signal seen through a [`Dac`]: piecewise constant, jumps at update instants.
pub struct DacSignal {
    /// Command signal.
    pub inner: Box<dyn Signal>,
    /// Converter.
    pub dac: Dac,
}

impl Signal for DacSignal {
    fn eval(&self, t: f64, left: bool) -> (f64, f64) {
        let x = t * self.dac.rate_hz;
        let k = if left && t > 0.0 {
            (x - 1e-9).ceil() - 1.0
        } else {
            (x + 1e-9).floor()
        };
        let k = k.max(0.0);
        (
            self.dac.quantise(self.inner.value(k / self.dac.rate_hz)),
            0.0,
        )
    }
    fn breakpoints(&self, t0: f64, t1: f64, out: &mut Vec<f64>) {
        let mut k = (t0 * self.dac.rate_hz + 1e-9).floor() + 1.0;
        loop {
            let t = k / self.dac.rate_hz;
            if t > t1 + 1e-15 * t1.abs() {
                break;
            }
            out.push(t.min(t1));
            k += 1.0;
        }
    }
    fn is_piecewise_constant(&self) -> bool {
        true
    }
}

/// The set of switched-on effects.
#[derive(Debug, Clone, PartialEq, Default)]
pub struct Effects {
    /// Creep.
    pub creep: Option<Creep>,
    /// Thermal drift.
    pub drift: Option<ThermalDrift>,
    /// Sensor delay, s.
    pub sensor_delay_s: Option<f64>,
    /// Amplifier.
    pub amplifier: Option<Amplifier>,
    /// Sensor noise.
    pub noise: Option<SensorNoise>,
    /// ADC quantisation step, m.
    pub adc_lsb_m: Option<f64>,
    /// DAC.
    pub dac: Option<Dac>,
    /// Electrostrictive coefficient, 1/V.
    pub electrostriction_per_v: Option<f64>,
    /// Cross-axis coupling (xy, yx).
    pub coupling: Option<[f64; 2]>,
    /// Dielectric lag of the stacks' hysteresis, s.
    pub dielectric_lag_s: Option<f64>,
    /// Rate scale ṙ₀ of the rate-dependent Bouc-Wen, V/s.
    pub hysteresis_rate_scale_v_per_s: Option<f64>,
    /// Second resonance mode.
    pub second_mode: Option<SecondMode>,
}

struct Kv<'a> {
    name: &'a str,
    pairs: Vec<(&'a str, &'a str)>,
    used: Vec<bool>,
}

impl<'a> Kv<'a> {
    fn num(&mut self, key: &str, default: f64) -> Result<f64, EffectError> {
        match self.pairs.iter().position(|(k, _)| *k == key) {
            None => Ok(default),
            Some(i) => {
                self.used[i] = true;
                parse_num(key, self.pairs[i].1)
            }
        }
    }
    fn list(&mut self, key: &str, default: &[f64]) -> Result<Vec<f64>, EffectError> {
        match self.pairs.iter().position(|(k, _)| *k == key) {
            None => Ok(default.to_vec()),
            Some(i) => {
                self.used[i] = true;
                self.pairs[i]
                    .1
                    .split('/')
                    .map(|s| parse_num(key, s))
                    .collect()
            }
        }
    }
    fn finish(&self, valid: &'static str) -> Result<(), EffectError> {
        match self.used.iter().position(|u| !u) {
            Some(i) => Err(EffectError::UnknownKey {
                effect: self.name.to_string(),
                key: self.pairs[i].0.to_string(),
                valid,
            }),
            None => Ok(()),
        }
    }
}

fn parse_num(key: &str, v: &str) -> Result<f64, EffectError> {
    let t = v.trim();
    let x: f64 = if t == "inf" {
        f64::INFINITY
    } else {
        t.parse().map_err(|_| EffectError::BadValue {
            key: key.into(),
            given: v.into(),
            reason: "not a number",
        })?
    };
    if x.is_nan() {
        return Err(EffectError::BadValue {
            key: key.into(),
            given: v.into(),
            reason: "not a number",
        });
    }
    Ok(x)
}

fn pos(key: &str, x: f64) -> Result<f64, EffectError> {
    if x > 0.0 {
        Ok(x)
    } else {
        Err(EffectError::BadValue {
            key: key.into(),
            given: x.to_string(),
            reason: "must be > 0",
        })
    }
}

impl Effects {
    /// Switches on one effect from `name:key=value,...` (see [`EFFECT_HELP`]).
    pub fn add_spec(&mut self, spec: &str) -> Result<(), EffectError> {
        let (name, rest) = spec.split_once(':').unwrap_or((spec, ""));
        let name = name.trim();
        let mut pairs = Vec::new();
        for item in rest.split(',').filter(|s| !s.trim().is_empty()) {
            let (k, v) = item.split_once('=').ok_or(EffectError::BadValue {
                key: item.into(),
                given: item.into(),
                reason: "expected key=value",
            })?;
            pairs.push((k.trim(), v.trim()));
        }
        let used = vec![false; pairs.len()];
        let mut kv = Kv { name, pairs, used };
        match name {
            "creep" => {
                let taus = kv.list("tau", &[0.1, 1.0, 10.0])?;
                let weights = kv.list("weight", &[0.01, 0.01, 0.01])?;
                kv.finish("tau, weight")?;
                if taus.len() != weights.len() || taus.iter().any(|t| !(*t > 0.0)) {
                    return Err(EffectError::BadValue {
                        key: "tau/weight".into(),
                        given: format!("{taus:?} / {weights:?}"),
                        reason: "equal-length lists, every tau > 0",
                    });
                }
                self.creep = Some(Creep {
                    elements: taus.into_iter().zip(weights).collect(),
                });
            }
            "drift" => {
                self.drift = Some(ThermalDrift {
                    rate_m_per_s: kv.num("rate", 1e-9)?,
                    amplitude_m: kv.num("amplitude", 0.0)?,
                    time_constant_s: pos("tau", kv.num("tau", 60.0)?)?,
                });
                kv.finish("rate, amplitude, tau")?;
            }
            "delay" => {
                self.sensor_delay_s = Some(pos("s", kv.num("s", 1e-5)?)?);
                kv.finish("s")?;
            }
            "amplifier" => {
                self.amplifier = Some(Amplifier {
                    bandwidth_hz: pos("bandwidth_hz", kv.num("bandwidth_hz", 1e4)?)?,
                    slew_v_per_s: pos("slew_v_per_s", kv.num("slew_v_per_s", f64::INFINITY)?)?,
                });
                kv.finish("bandwidth_hz, slew_v_per_s")?;
            }
            "noise" => {
                let rms = kv.num("rms_m", 1e-9)?;
                let seed = kv.num("seed", 1.0)?;
                if !(rms >= 0.0 && seed >= 0.0 && seed.fract() == 0.0) {
                    return Err(EffectError::BadValue {
                        key: "rms_m/seed".into(),
                        given: format!("{rms}/{seed}"),
                        reason: "rms >= 0, seed a non-negative integer",
                    });
                }
                self.noise = Some(SensorNoise {
                    rms_m: rms,
                    seed: seed as u64,
                });
                kv.finish("rms_m, seed")?;
            }
            "adc" => {
                self.adc_lsb_m = Some(pos("lsb_m", kv.num("lsb_m", 1e-9)?)?);
                kv.finish("lsb_m")?;
            }
            "dac" => {
                let bits = kv.num("bits", 16.0)?;
                if !(1.0..=32.0).contains(&bits) || bits.fract() != 0.0 {
                    return Err(EffectError::BadValue {
                        key: "bits".into(),
                        given: bits.to_string(),
                        reason: "integer 1..32",
                    });
                }
                let dac = Dac {
                    bits: bits as u32,
                    min_v: kv.num("min", 0.0)?,
                    max_v: kv.num("max", 120.0)?,
                    rate_hz: pos("rate_hz", kv.num("rate_hz", 1e5)?)?,
                };
                if !(dac.max_v > dac.min_v) {
                    return Err(EffectError::BadValue {
                        key: "max".into(),
                        given: dac.max_v.to_string(),
                        reason: "max > min",
                    });
                }
                kv.finish("bits, min, max, rate_hz")?;
                self.dac = Some(dac);
            }
            "electrostriction" => {
                self.electrostriction_per_v = Some(kv.num("per_v", 1e-3)?);
                kv.finish("per_v")?;
            }
            "coupling" => {
                self.coupling = Some([kv.num("xy", 0.01)?, kv.num("yx", 0.01)?]);
                kv.finish("xy, yx")?;
            }
            "dielectric-lag" => {
                self.dielectric_lag_s = Some(pos("tau", kv.num("tau", 1e-3)?)?);
                kv.finish("tau")?;
            }
            "rate-bouc-wen" => {
                self.hysteresis_rate_scale_v_per_s = Some(pos("rate", kv.num("rate", 1e5)?)?);
                kv.finish("rate")?;
            }
            "second-mode" => {
                self.second_mode = Some(SecondMode {
                    frequency_hz: pos("freq_hz", kv.num("freq_hz", 480e3)?)?,
                    damping_ratio: pos("zeta", kv.num("zeta", 0.05)?)?,
                    participation: kv.num("participation", 0.05)?,
                });
                kv.finish("freq_hz, zeta, participation")?;
            }
            other => {
                return Err(EffectError::UnknownEffect {
                    given: other.into(),
                })
            }
        }
        Ok(())
    }

    /// Puts the plant-internal effects (electrostriction, coupling, second mode) into the plant; refuses
    /// those the plant does not have.
    pub fn apply_to_plant(&self, plant: &mut PlantKind) -> Result<(), PlantError> {
        if let Some(e) = self.electrostriction_per_v {
            plant.as_plant_mut().set_electrostriction(e);
        }
        match plant {
            PlantKind::XyStage(p) => {
                if let Some(c) = self.coupling {
                    p.coupling = c;
                }
                if let Some(tau) = self.dielectric_lag_s {
                    p.dielectric_lag_s = tau;
                }
                if let Some(rate) = self.hysteresis_rate_scale_v_per_s {
                    p.hysteresis_rate_scale_v_per_s = rate;
                }
            }
            PlantKind::Stage(p) if self.coupling.is_none() => {
                if let Some(tau) = self.dielectric_lag_s {
                    p.dielectric_lag_s = tau;
                }
                if let Some(rate) = self.hysteresis_rate_scale_v_per_s {
                    p.hysteresis_rate_scale_v_per_s = rate;
                }
            }
            other
                if self.coupling.is_some()
                    || self.dielectric_lag_s.is_some()
                    || self.hysteresis_rate_scale_v_per_s.is_some() =>
            {
                return Err(PlantError::Unsupported {
                    plant: other.as_plant().name(),
                    what: "cross-axis coupling (xy-stage only), a dielectric lag or a \
                           rate-dependent Bouc-Wen (xy-stage and stage only)"
                        .into(),
                })
            }
            _ => {}
        }
        match plant {
            PlantKind::Nac2024(p) => p.second_mode = self.second_mode,
            other if self.second_mode.is_some() => {
                return Err(PlantError::Unsupported {
                    plant: other.as_plant().name(),
                    what: "a second resonance mode (nac2024 only)".into(),
                })
            }
            _ => {}
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parse_and_errors() {
        let mut e = Effects::default();
        e.add_spec("creep:tau=1/10,weight=0.02/0.03").unwrap();
        assert_eq!(
            e.creep.as_ref().unwrap().elements,
            vec![(1.0, 0.02), (10.0, 0.03)]
        );
        e.add_spec("amplifier:bandwidth_hz=2000,slew_v_per_s=1e4")
            .unwrap();
        let msg = e.add_spec("creeep").unwrap_err().to_string();
        assert!(
            msg.contains("creeep") && msg.contains("second-mode"),
            "{msg}"
        );
        let msg = e.add_spec("noise:rms=1").unwrap_err().to_string();
        assert!(msg.contains("rms") && msg.contains("rms_m"), "{msg}");
        let msg = e.add_spec("delay:s=x").unwrap_err().to_string();
        assert!(msg.contains("`s`") && msg.contains('x'), "{msg}");
    }

    #[test]
    fn coupling_refused_on_single_axis_plants() {
        let mut e = Effects::default();
        e.add_spec("coupling").unwrap();
        let mut p = PlantKind::from_name("nac2024").unwrap();
        assert!(e
            .apply_to_plant(&mut p)
            .unwrap_err()
            .to_string()
            .contains("coupling"));
        let mut e = Effects::default();
        e.add_spec("second-mode").unwrap();
        let mut p = PlantKind::from_name("xy-stage").unwrap();
        assert!(e.apply_to_plant(&mut p).is_err());
    }

    #[test]
    fn dac_quantises_and_holds() {
        let dac = Dac {
            bits: 8,
            min_v: 0.0,
            max_v: 255.0,
            rate_hz: 10.0,
        };
        let s = DacSignal {
            inner: Box::new(crate::signal::Sine {
                amplitude_v: 100.0,
                offset_v: 100.0,
                frequency_hz: 1.0,
                phase_rad: 0.0,
            }),
            dac,
        };
        assert_eq!(
            s.value(0.15),
            (100.0 + 100.0 * (2.0 * std::f64::consts::PI * 0.1).sin()).round()
        );
        assert_eq!(s.eval(0.2, true).0, s.value(0.15));
        assert_ne!(s.eval(0.2, false).0, s.value(0.15));
    }
}
