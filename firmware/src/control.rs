//! The per-tick loop body: ADC → displacement → feed-forward → safety guard → DAC.
//!
//! [`tick`] is deliberately small and generic: it works with any [`DacWrite`]/[`AdcRead`]
//! (the SPI drivers on the board, the simulated plant under QEMU and on the host), and takes
//! the feed-forward as a closure `FnMut(reference_m, measured_m) -> requested actuator volts`,
//! so the inverse hysteresis compensator from `piezo-core` can be dropped in without touching
//! the I/O or the safety path.
//!
//! Per tick:
//!
//! ```text
//! x_meas = (ADC code → volts) · sensor m/V
//! u_req  = feedforward(x_ref, x_meas)            actuator volts
//! u      = guard(u_req)                          window, slew, NaN hold (crate::safety)
//! code   = DacCode::from_volts(u / G_amp)        saturating, NaN → 0 V
//! ```
//!
//! On an ADC error the DAC is not written (the DAC holds its last output) and the error is
//! returned; the caller decides whether to stop.

use crate::codes::{DacCode, SensorScale};
use crate::converter::{AdcRead, DacWrite, Error, ErrorKind};
use crate::safety::{GuardState, SafetyLimits};

/// The converters a loop drives, and which channel of each.
#[derive(Debug)]
pub struct LoopIo<D: DacWrite, A: AdcRead> {
    /// Drives the piezo amplifier input.
    pub dac: D,
    /// DAC channel wired to the amplifier.
    pub dac_channel: D::Channel,
    /// Reads the displacement sensor.
    pub adc: A,
    /// ADC channel wired to the sensor.
    pub adc_channel: A::Channel,
}

/// Validated loop settings.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct LoopConfig {
    sensor: SensorScale,
    amplifier_gain_v_per_v: f32,
    limits: SafetyLimits,
}

impl LoopConfig {
    /// Settings; `None` unless the amplifier gain is finite and positive. The ADC codes are
    /// read with the default ±10.24 V transfer function ([`crate::codes::AdcCode::to_volts`]).
    pub fn new(
        sensor: SensorScale,
        amplifier_gain_v_per_v: f32,
        limits: SafetyLimits,
    ) -> Option<Self> {
        (amplifier_gain_v_per_v.is_finite() && amplifier_gain_v_per_v > 0.0).then_some(Self {
            sensor,
            amplifier_gain_v_per_v,
            limits,
        })
    }

    /// The output safety limits, in actuator volts.
    pub fn limits(&self) -> &SafetyLimits {
        &self.limits
    }

    /// The sensor scale.
    pub fn sensor(&self) -> SensorScale {
        self.sensor
    }

    /// Amplifier gain, actuator volts per DAC volt.
    pub fn amplifier_gain_v_per_v(&self) -> f32 {
        self.amplifier_gain_v_per_v
    }
}

/// What one tick measured and did.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct TickOutput {
    /// Displacement read at the start of the tick, metres.
    pub measured_m: f32,
    /// `reference_m − measured_m`.
    pub tracking_error_m: f32,
    /// Feed-forward output before the guard, actuator volts (may be NaN).
    pub requested_volts: f32,
    /// Guarded output, actuator volts.
    pub applied_volts: f32,
    /// Code written to the DAC.
    pub code: DacCode,
}

/// A failed tick: which converter failed.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
pub enum TickError<DE, AE> {
    /// Reading the sensor failed; the DAC was not written.
    Adc(AE),
    /// Writing the DAC failed.
    Dac(DE),
}

impl<DE: Error, AE: Error> Error for TickError<DE, AE> {
    fn kind(&self) -> ErrorKind {
        match self {
            TickError::Adc(e) => e.kind(),
            TickError::Dac(e) => e.kind(),
        }
    }
}

/// One loop tick (see module docs). Never panics.
#[inline]
pub fn tick<D, A, F>(
    io: &mut LoopIo<D, A>,
    config: &LoopConfig,
    guard: &mut GuardState,
    reference_m: f32,
    mut feedforward: F,
) -> Result<TickOutput, TickError<D::Error, A::Error>>
where
    D: DacWrite,
    A: AdcRead,
    F: FnMut(f32, f32) -> f32,
{
    let code_in = io.adc.read_code(io.adc_channel).map_err(TickError::Adc)?;
    let measured_m = config.sensor.metres(code_in.to_volts());
    let requested_volts = feedforward(reference_m, measured_m);
    let applied_volts = config.limits.apply(guard, requested_volts);
    let code = DacCode::from_volts(applied_volts / config.amplifier_gain_v_per_v);
    io.dac
        .write_code(io.dac_channel, code)
        .map_err(TickError::Dac)?;
    Ok(TickOutput {
        measured_m,
        tracking_error_m: reference_m - measured_m,
        requested_volts,
        applied_volts,
        code,
    })
}

/// Running tracking-error statistics (RMS and peak).
#[derive(Clone, Copy, Debug, Default, PartialEq)]
pub struct TrackingStats {
    count: u32,
    sum_sq_m2: f32,
    max_abs_m: f32,
}

impl TrackingStats {
    /// Adds one error sample (non-finite samples make the RMS and peak infinite).
    pub fn push(&mut self, error_m: f32) {
        let e = if error_m.is_finite() {
            error_m
        } else {
            f32::INFINITY
        };
        self.count = self.count.saturating_add(1);
        self.sum_sq_m2 += e * e;
        self.max_abs_m = self.max_abs_m.max(e.abs());
    }

    /// Number of samples.
    pub fn count(&self) -> u32 {
        self.count
    }

    /// Root mean square error, metres (0 with no samples).
    pub fn rms_m(&self) -> f32 {
        if self.count == 0 {
            0.0
        } else {
            libm::sqrtf(self.sum_sq_m2 / self.count as f32)
        }
    }

    /// Largest absolute error, metres.
    pub fn max_abs_m(&self) -> f32 {
        self.max_abs_m
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::codes::AdcCode;
    use crate::converter::ErrorType;
    use core::convert::Infallible;

    /// A DAC that records the last code, and an ADC that returns a fixed code or fails.
    struct RecDac(Option<DacCode>, bool);
    struct FixedAdc(Option<AdcCode>);
    #[derive(Debug, PartialEq)]
    struct Broken;
    impl Error for Broken {
        fn kind(&self) -> ErrorKind {
            ErrorKind::Other
        }
    }
    impl ErrorType for RecDac {
        type Error = Broken;
    }
    impl DacWrite for RecDac {
        type Channel = ();
        fn write_code(&mut self, _: (), code: DacCode) -> Result<(), Broken> {
            if self.1 {
                return Err(Broken);
            }
            self.0 = Some(code);
            Ok(())
        }
    }
    impl ErrorType for FixedAdc {
        type Error = Broken;
    }
    impl AdcRead for FixedAdc {
        type Channel = ();
        fn read_code(&mut self, _: ()) -> Result<AdcCode, Broken> {
            self.0.ok_or(Broken)
        }
    }

    fn config() -> LoopConfig {
        LoopConfig::new(
            SensorScale::new(1.5e-6).unwrap(),
            20.0,
            SafetyLimits::new(0.0, 100.0, 2.0).unwrap(),
        )
        .unwrap()
    }

    fn io(adc: Option<AdcCode>, dac_fails: bool) -> LoopIo<RecDac, FixedAdc> {
        LoopIo {
            dac: RecDac(None, dac_fails),
            dac_channel: (),
            adc: FixedAdc(adc),
            adc_channel: (),
        }
    }

    #[test]
    fn tick_measures_guards_and_writes() {
        let cfg = config();
        let mut io = io(Some(AdcCode::from_volts(2.0)), false);
        let mut guard = cfg.limits().state(10.0);
        let mut seen = (0.0, 0.0);
        let out = tick(&mut io, &cfg, &mut guard, 4e-6, |r, m| {
            seen = (r, m);
            11.0
        })
        .unwrap();
        assert_eq!(seen.0, 4e-6);
        assert!((seen.1 - 3e-6).abs() < 1e-9);
        assert_eq!(out.applied_volts, 11.0);
        assert_eq!(out.code, DacCode::from_volts(11.0 / 20.0));
        assert_eq!(io.dac.0, Some(out.code));
        assert!((out.tracking_error_m - 1e-6).abs() < 1e-9);
    }

    #[test]
    fn nan_feedforward_holds_last_output() {
        let cfg = config();
        let mut io = io(Some(AdcCode::MID_SCALE), false);
        let mut guard = cfg.limits().state(10.0);
        let out = tick(&mut io, &cfg, &mut guard, 0.0, |_, _| f32::NAN).unwrap();
        assert_eq!(out.applied_volts, 10.0);
        assert_eq!(guard.counters().non_finite, 1);
    }

    #[test]
    fn adc_error_skips_dac_write() {
        let cfg = config();
        let mut io = io(None, false);
        let mut guard = cfg.limits().state(0.0);
        let err = tick(&mut io, &cfg, &mut guard, 0.0, |_, _| 5.0).unwrap_err();
        assert_eq!(err, TickError::Adc(Broken));
        assert_eq!(err.kind(), ErrorKind::Other);
        assert_eq!(io.dac.0, None);
    }

    #[test]
    fn dac_error_is_reported() {
        let cfg = config();
        let mut io = io(Some(AdcCode::MID_SCALE), true);
        let mut guard = cfg.limits().state(0.0);
        let err = tick(&mut io, &cfg, &mut guard, 0.0, |_, _| 5.0).unwrap_err();
        assert_eq!(err, TickError::Dac(Broken));
    }

    #[test]
    fn infallible_converters_compose() {
        // The simulated plant's error type is Infallible; TickError<Infallible, Infallible>
        // still implements Error.
        fn kind_of<E: Error>(_: Option<E>) {}
        kind_of::<TickError<Infallible, Infallible>>(None);
    }

    #[test]
    fn loop_config_rejects_bad_gain() {
        let s = SensorScale::new(1.0).unwrap();
        let l = SafetyLimits::new(0.0, 1.0, 1.0).unwrap();
        assert!(LoopConfig::new(s, 0.0, l).is_none());
        assert!(LoopConfig::new(s, f32::NAN, l).is_none());
        assert!(LoopConfig::new(s, -2.0, l).is_none());
    }

    #[test]
    fn tracking_stats() {
        let mut s = TrackingStats::default();
        assert_eq!(s.rms_m(), 0.0);
        s.push(3.0);
        s.push(-4.0);
        assert_eq!(s.count(), 2);
        assert!((s.rms_m() - libm::sqrtf(12.5)).abs() < 1e-6);
        assert_eq!(s.max_abs_m(), 4.0);
        s.push(f32::NAN);
        assert_eq!(s.max_abs_m(), f32::INFINITY);
    }
}
